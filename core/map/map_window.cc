#include "core/map/map_window.h"

#include <algorithm>
#include <optional>
#include <unordered_set>

#include <Eigen/Cholesky>
#include <Eigen/CholmodSupport>

#include "absl/strings/str_cat.h"
#include "core/map/dense_kernels.h"
#include "core/map/sparse_ordering.h"
#include "core/map/sparse_threads.h"

namespace crowdmap {

// Small windows (a loop's map) are factorised densely: CHOLMOD's symbolic analysis would cost
// more than the factorisation.
constexpr int kDenseWindowDims = 600;

// CHOLMOD's supernodal factor (which Eigen's wrapper keeps to itself) of a matrix given by its
// lower triangle, already in a fill-reducing order: analysed in that order, as it is.
class SupernodalLLT : public Eigen::CholmodSupernodalLLT<Eigen::SparseMatrix<double>, Eigen::Lower> {
 public:
  // The symbolic analysis of `a`'s pattern without a permutation of CHOLMOD's own (nor its
  // postorder, a permutation too): CHOLMOD then reads `a` as it is, where a permutation costs it
  // two transposes of the matrix in the analysis and two in each factorisation.
  bool AnalyzeInGivenOrder(const Eigen::SparseMatrix<double>& a) {
    FactorizeOnThisThreadOnly();
    if (m_cholmodFactor != nullptr) cholmod_free_factor(&m_cholmodFactor, &cholmod());
    cholmod_sparse view = Eigen::viewAsCholmod(a.selfadjointView<Eigen::Lower>());
    cholmod().nmethods = 1;
    cholmod().method[0].ordering = CHOLMOD_NATURAL;
    cholmod().postorder = 0;
    m_cholmodFactor = cholmod_analyze(&view, &cholmod());
    m_isInitialized = true;
    m_analysisIsOk = m_cholmodFactor != nullptr;
    m_factorizationIsOk = false;
    m_info = m_analysisIsOk ? Eigen::Success : Eigen::NumericalIssue;
    return m_analysisIsOk;
  }
  const cholmod_factor& factor() const { return *m_cholmodFactor; }
};

namespace {

// The arrays of CHOLMOD's supernodal factor `l` (int indices, real values): each supernode's first
// column, its row indices' and its values' starts, the row indices, the values.
struct SupernodalArrays {
  const int* super;
  const int* pi;
  const int* px;
  const int* s;
  const double* x;
};
SupernodalArrays ArraysOf(const cholmod_factor& l) {
  return {static_cast<const int*>(l.super), static_cast<const int*>(l.pi), static_cast<const int*>(l.px),
          static_cast<const int*>(l.s), static_cast<const double*>(l.x)};
}

// A window's information by 2 x 2 blocks: its diagonal blocks and, for each landmark j, the blocks
// of the window landmarks linked to it that come before it (i < j): the upper triangle, each link
// once. The factorisation takes it in the order of a fill-reducing permutation of the landmarks
// (ToSparseLower), written straight into compressed columns (sorting and summing triplets cost as
// much as the rest of the assembly).
class UpperBlocks {
 public:
  explicit UpperBlocks(int n) : diagonal_(n, Eigen::Matrix2d::Zero()), rows_(n), values_(n) {}

  int size() const { return static_cast<int>(diagonal_.size()); }
  void AddDiagonal(int j, const Eigen::Matrix2d& block) { diagonal_[j] += block; }
  // The block of a link between i < j at (2i, 2j): each link once, and a column's links in
  // increasing i (the order a window visits its landmarks in), which keeps each column's rows sorted.
  void AddAbove(int i, int j, const Eigen::Matrix2d& block) {
    rows_[j].push_back(i);
    values_[j].push_back(block);
  }
  // Adds `block` at (2i, 2j), i <= j. True when no block was there: the pattern grew.
  bool Add(int i, int j, const Eigen::Matrix2d& block) {
    if (i == j) {
      diagonal_[j] += block;
      return false;
    }
    std::vector<int>& rows = rows_[j];
    const auto it = std::lower_bound(rows.begin(), rows.end(), i);
    const auto at = it - rows.begin();
    if (it == rows.end() || *it != i) {
      rows.insert(it, i);
      values_[j].insert(values_[j].begin() + at, block);
      return true;
    }
    values_[j][at] += block;
    return false;
  }

  // Column j's rows (the landmarks i < j linked to it).
  const std::vector<std::vector<int>>& rows() const { return rows_; }

  // The lower triangle of the information with landmark i at block position `position[i]`: P A P^T,
  // each column's rows sorted (the form CHOLMOD's supernodal factorisation reads without a copy,
  // where a permutation of its own costs it two transposes of the matrix).
  Eigen::SparseMatrix<double> ToSparseLower(const std::vector<int>& position) const {
    const int n = size();
    // Each link as (row position hi, column position lo) with its block oriented rows of hi, columns
    // of lo, bucketed by hi so that the columns fill in increasing row order. The links are read in
    // order (the rows alone to count them); the buckets hold the blocks themselves, so that the
    // last pass reads them in order too and only its writes scatter.
    struct Below {
      int lo;
      Eigen::Matrix2d block;
    };
    std::vector<int> start(n + 1, 0), per_column(n, 0);
    for (int j = 0; j < n; ++j) {
      const int pj = position[j];
      for (int row : rows_[j]) {
        const int pi = position[row];
        ++start[std::max(pi, pj) + 1];
        ++per_column[std::min(pi, pj)];
      }
    }
    for (int k = 0; k < n; ++k) start[k + 1] += start[k];
    std::vector<Below> below(start[n]);
    {
      std::vector<int> next(start.begin(), start.end() - 1);
      for (int j = 0; j < n; ++j) {
        const int pj = position[j];
        const std::vector<int>& rows = rows_[j];
        for (size_t k = 0; k < rows.size(); ++k) {
          const int pi = position[rows[k]];
          // The block holds rows of landmark rows[k], columns of landmark j.
          Below& b = below[next[std::max(pi, pj)]++];
          b.lo = std::min(pi, pj);
          b.block = pj > pi ? values_[j][k].transpose() : values_[j][k];
        }
      }
    }
    std::vector<int> landmark_at(n);
    for (int i = 0; i < n; ++i) landmark_at[position[i]] = i;
    Eigen::SparseMatrix<double> out(2 * n, 2 * n);
    out.resizeNonZeros(static_cast<Eigen::Index>(3 * n + 4 * start[n]));
    int* outer = out.outerIndexPtr();
    int* inner = out.innerIndexPtr();
    double* value = out.valuePtr();
    std::vector<int> fill(2 * n);
    int at = 0;
    for (int k = 0; k < n; ++k) {
      const Eigen::Matrix2d& d = diagonal_[landmark_at[k]];
      outer[2 * k] = at;
      inner[at] = 2 * k, value[at++] = d(0, 0);
      inner[at] = 2 * k + 1, value[at++] = d(1, 0);
      fill[2 * k] = at;
      at += 2 * per_column[k];
      outer[2 * k + 1] = at;
      inner[at] = 2 * k + 1, value[at++] = d(1, 1);
      fill[2 * k + 1] = at;
      at += 2 * per_column[k];
    }
    outer[2 * n] = at;
    for (int hi = 0; hi < n; ++hi) {
      for (int e = start[hi]; e < start[hi + 1]; ++e) {
        const Below& b = below[e];
        for (int c = 0; c < 2; ++c) {
          int& f = fill[2 * b.lo + c];
          for (int r = 0; r < 2; ++r) {
            inner[f] = 2 * hi + r;
            value[f++] = b.block(r, c);
          }
        }
      }
    }
    return out;
  }

  // The lower triangle, dense, in the landmarks' order (zeros above the diagonal).
  Eigen::MatrixXd ToDenseLower() const {
    const int n = size();
    Eigen::MatrixXd out = Eigen::MatrixXd::Zero(2 * n, 2 * n);
    for (int j = 0; j < n; ++j) {
      out.block<2, 2>(2 * j, 2 * j) = diagonal_[j];
      out(2 * j, 2 * j + 1) = 0.0;
      for (size_t k = 0; k < rows_[j].size(); ++k) {
        out.block<2, 2>(2 * j, 2 * rows_[j][k]) = values_[j][k].transpose();
      }
    }
    return out;
  }

 private:
  std::vector<Eigen::Matrix2d> diagonal_;
  // Column j's links: the landmarks above the diagonal (i < j) and their blocks, apart, so that
  // the passes that need only the rows read only them.
  std::vector<std::vector<int>> rows_;
  std::vector<std::vector<Eigen::Matrix2d>> values_;
};

}  // namespace

// Factorisation of a window's information, given by its blocks. A small window is factorised
// densely in the landmarks' order; a larger one sparsely, in a fill-reducing order of its
// landmarks (position_), which the methods below translate from and to the landmarks' order.
class MapWindow::Factor {
 public:
  explicit Factor(const UpperBlocks& blocks) {
    if (2 * blocks.size() <= kDenseWindowDims) {
      dense_ = blocks.ToDenseLower();
      ok_ = CholeskyInPlace(dense_);
      return;
    }
    sparse_ = std::make_unique<SupernodalLLT>();
    order_ = PostorderedFillReducingOrder(blocks.rows(), &sparse_->cholmod());
    if (order_.empty()) {  // AMD failed (out of memory): the landmarks' own order
      order_.resize(blocks.size());
      for (int i = 0; i < blocks.size(); ++i) order_[i] = i;
    }
    position_.resize(order_.size());
    for (size_t k = 0; k < order_.size(); ++k) position_[order_[k]] = static_cast<int>(k);
    matrix_ = blocks.ToSparseLower(position_);
    ok_ = sparse_->AnalyzeInGivenOrder(matrix_) && Numeric();
  }
  Eigen::ComputationInfo info() const { return ok_ ? Eigen::Success : Eigen::NumericalIssue; }
  // Factorises `blocks` in place of the ones the factor was made with, whose pattern they must have
  // (or a part of it): the order and CHOLMOD's symbolic analysis are reused.
  bool Refactorize(const UpperBlocks& blocks) {
    if (!sparse_) {
      dense_ = blocks.ToDenseLower();
      ok_ = CholeskyInPlace(dense_);
      return ok_;
    }
    matrix_ = blocks.ToSparseLower(position_);
    ok_ = Numeric();
    return ok_;
  }
  // The inverse of the information, dense, in the landmarks' order.
  absl::StatusOr<Eigen::MatrixXd> DenseInverse() const {
    Eigen::MatrixXd inverse;
    if (sparse_) {
      const int dims = static_cast<int>(matrix_.rows());
      inverse = Eigen::MatrixXd::Zero(dims, dims);
      for (int c = 0; c < dims; ++c) {
        for (Eigen::SparseMatrix<double>::InnerIterator it(matrix_, c); it; ++it) {
          const int a = Original(static_cast<int>(it.row())), b = Original(c);
          inverse(std::max(a, b), std::min(a, b)) = it.value();
        }
      }
      if (!CholeskyInPlace(inverse)) return absl::FailedPreconditionError("map information is not positive definite");
    } else {
      inverse = dense_;
    }
    InverseFromCholeskyInPlace(inverse);
    return inverse;
  }
  template <typename Rhs>
  Eigen::MatrixXd solve(const Rhs& b) const {
    if (sparse_) {
      Eigen::MatrixXd in_order(b.rows(), b.cols());
      for (int r = 0; r < static_cast<int>(b.rows()); ++r) in_order.row(Ordered(r)) = b.row(r);
      const Eigen::MatrixXd solved = sparse_->solve(in_order);
      Eigen::MatrixXd x(b.rows(), b.cols());
      for (int r = 0; r < static_cast<int>(b.rows()); ++r) x.row(r) = solved.row(Ordered(r));
      return x;
    }
    Eigen::MatrixXd x = b;
    SolveLowerInPlace(dense_, x);
    dense_.triangularView<Eigen::Lower>().transpose().solveInPlace(x);
    return x;
  }

  // The inverse's block over `rows` (rows of the factorised matrix): X^T X with X = L^-1 P E,
  // E the unit columns of `rows`. A column of X is non-zero only on the columns of L that are
  // ancestors of its row in the elimination tree, so the forward solve visits only the supernodes
  // on the paths from `rows` to the roots; the backward solve is never needed.
  Eigen::MatrixXd InverseBlock(const std::vector<int>& rows) const {
    const int m = static_cast<int>(rows.size());
    if (sparse_ && column_super_.empty()) {  // not a supernodal factor CHOLMOD could be read from
      Eigen::MatrixXd unit = Eigen::MatrixXd::Zero(sparse_->rows(), m);
      for (int c = 0; c < m; ++c) unit(rows[c], c) = 1.0;
      const Eigen::MatrixXd columns = solve(unit);
      const Eigen::MatrixXd cov = columns(rows, Eigen::all);
      return 0.5 * (cov + cov.transpose());
    }
    if (!sparse_) {
      Eigen::MatrixXd x = Eigen::MatrixXd::Zero(dense_.rows(), m);
      for (int c = 0; c < m; ++c) x(rows[c], c) = 1.0;
      SolveLowerInPlace(dense_, x);
      Eigen::MatrixXd gram = Eigen::MatrixXd::Zero(m, m);
      AddGramLower(x, gram);
      return gram.selfadjointView<Eigen::Lower>();
    }
    const cholmod_factor& l = sparse_->factor();
    const auto [super, pi, px, ls, lx] = ArraysOf(l);
    // X's columns sorted by the supernode of their row: in a postordered tree the rows below a
    // supernode s are those of supernodes first_descendant_[s]..s, so the columns non-zero at s
    // are one contiguous range.
    std::vector<int> order(m), seed_super(m);
    for (int c = 0; c < m; ++c) order[c] = c;
    for (int c = 0; c < m; ++c) seed_super[c] = column_super_[permuted_[rows[c]]];
    std::sort(order.begin(), order.end(), [&](int a, int b) { return seed_super[a] < seed_super[b]; });
    std::vector<int> sorted_super(m);
    for (int k = 0; k < m; ++k) sorted_super[k] = seed_super[order[k]];
    const auto active = [&](int s) -> std::pair<int, int> {
      if (!postordered_) return {0, m};
      const auto lo = std::lower_bound(sorted_super.begin(), sorted_super.end(), first_descendant_[s]);
      const auto hi = std::upper_bound(lo, sorted_super.end(), s);
      return {static_cast<int>(lo - sorted_super.begin()), static_cast<int>(hi - sorted_super.begin())};
    };
    // The supernodes on the paths to the roots, in increasing order (a parent follows its
    // children), and the position of each of their columns in X.
    std::vector<int> reach;
    std::vector<char> seen(l.nsuper, 0);
    for (int c = 0; c < m; ++c) {
      for (int s = seed_super[c]; s >= 0 && !seen[s]; s = parent_[s]) {
        seen[s] = 1;
        reach.push_back(s);
      }
    }
    std::sort(reach.begin(), reach.end());
    std::vector<int> start(l.nsuper, -1);  // supernode -> its first row in X
    int total = 0;
    for (int s : reach) {
      start[s] = total;
      total += super[s + 1] - super[s];
    }
    auto position = [&](int column) {
      const int s = column_super_[column];
      return start[s] + column - super[s];
    };
    Eigen::MatrixXd x = Eigen::MatrixXd::Zero(total, m);
    for (int k = 0; k < m; ++k) x(position(permuted_[rows[order[k]]]), k) = 1.0;
    Eigen::MatrixXd below;
    Eigen::MatrixXd gram = Eigen::MatrixXd::Zero(m, m);
    for (int s : reach) {
      const auto [lo, hi] = active(s);
      if (lo == hi) continue;
      const int ncols = super[s + 1] - super[s], nrows = pi[s + 1] - pi[s];
      const Eigen::Map<const Eigen::MatrixXd> block(lx + px[s], nrows, ncols);
      auto xs = x.block(start[s], lo, ncols, hi - lo);
      SolveLowerInPlace(block.topRows(ncols), xs);
      // X's rows at s are final: their share of X^T X.
      AddGramLower(xs, gram.block(lo, lo, hi - lo, hi - lo));
      if (nrows == ncols) continue;
      Multiply(block.bottomRows(nrows - ncols), xs, &below);
      for (int t = 0; t < nrows - ncols; ++t) {
        x.block(position(ls[pi[s] + ncols + t]), lo, 1, hi - lo) -= below.row(t);
      }
    }
    Eigen::MatrixXd out(m, m);
    for (int a = 0; a < m; ++a) {
      for (int b = 0; b <= a; ++b) {
        const int i = std::max(a, b), j = std::min(a, b);
        out(order[a], order[b]) = out(order[b], order[a]) = gram(i, j);
      }
    }
    return out;
  }

  // The inverse's 2x2 diagonal blocks (rows 2i and 2i + 1 of the factorised matrix, i = 0, 1, ...).
  // On a supernodal factor, from the inverse's entries on the factor's pattern (Takahashi's
  // recursion by supernodes, from the roots down): for a supernode with columns D and the rows R
  // below them,
  //   Y = L_RD L_DD^-1,  Sigma_RD = -Sigma_RR Y,  Sigma_DD = L_DD^-T L_DD^-1 - Y^T Sigma_RD,
  // where Sigma_RR lies on the pattern of the supernodes R belongs to, all done before (the rows
  // of a supernode form a clique of the filled graph). Dense products, as the factorisation's.
  std::vector<Eigen::Matrix2d> InverseDiagonalBlocks() const {
    const int n = static_cast<int>(sparse_ ? sparse_->rows() : dense_.rows());
    std::vector<Eigen::Matrix2d> out(n / 2);
    // A dense factor, or a sparse one CHOLMOD's supernodes could not be read from: the whole
    // inverse.
    const auto from_whole_inverse = [&] {
      std::vector<int> rows(n);
      for (int i = 0; i < n; ++i) rows[i] = i;
      Eigen::MatrixXd inverse;
      if (sparse_) {
        inverse = InverseBlock(rows);
      } else {
        inverse = dense_;
        InverseFromCholeskyInPlace(inverse);
      }
      for (int i = 0; i + 1 < n; i += 2) out[i / 2] = inverse.block<2, 2>(i, i);
      return out;
    };
    if (!sparse_ || column_super_.empty()) return from_whole_inverse();
    const cholmod_factor& l = sparse_->factor();
    const auto [super, pi, px, ls, lx] = ArraysOf(l);
    std::vector<double> sigma(px[l.nsuper]);  // the inverse on L's pattern, in L's layout
    // Position of `row` among the rows of the supernode holding column `col` (row >= col), from
    // `from` on; -1 when it is not on the pattern (the rows are sorted; never for a valid factor).
    auto locate = [&](int row, int col, int from) {
      const int t = column_super_[col];
      const int* begin = ls + pi[t];
      const int* it = std::lower_bound(begin + from, ls + pi[t + 1], row);
      return it != ls + pi[t + 1] && *it == row ? static_cast<int>(it - begin) : -1;
    };
    Eigen::MatrixXd dd_inverse, y, rr;
    for (int s = static_cast<int>(l.nsuper) - 1; s >= 0; --s) {
      const int k = super[s + 1] - super[s], nrows = pi[s + 1] - pi[s], r = nrows - k;
      const Eigen::Map<const Eigen::MatrixXd> block(lx + px[s], nrows, k);
      Eigen::Map<Eigen::MatrixXd> inverse(sigma.data() + px[s], nrows, k);
      dd_inverse.setIdentity(k, k);
      SolveLowerInPlace(block.topRows(k), dd_inverse);  // L_DD^-1
      dd_inverse.triangularView<Eigen::StrictlyUpper>().setZero();
      inverse.topRows(k).noalias() = dd_inverse.transpose() * dd_inverse;
      if (r == 0) continue;
      y.noalias() = block.bottomRows(r) * dd_inverse.triangularView<Eigen::Lower>();
      rr.resize(r, r);
      const int* below = ls + pi[s] + k;
      for (int b = 0; b < r; ++b) {
        const int col = below[b], t = column_super_[col], t_rows = pi[t + 1] - pi[t];
        const double* column = sigma.data() + px[t] + static_cast<size_t>(col - super[t]) * t_rows;
        int at = col - super[t];
        for (int a = b; a < r; ++a) {
          at = locate(below[a], col, at);
          if (at < 0) return from_whole_inverse();
          rr(a, b) = rr(b, a) = column[at];
        }
      }
      inverse.bottomRows(r).noalias() = -rr * y;
      inverse.topRows(k).noalias() -= y.transpose() * inverse.bottomRows(r);
    }
    for (int i = 0; i + 1 < n; i += 2) {
      const int a = permuted_[i], b = permuted_[i + 1];
      const int lo = std::min(a, b), hi = std::max(a, b);
      const auto entry = [&](int row, int col) {
        const int t = column_super_[col];
        return sigma[px[t] + static_cast<size_t>(col - super[t]) * (pi[t + 1] - pi[t]) + locate(row, col, col - super[t])];
      };
      out[i / 2] << entry(a, a), entry(hi, lo), entry(hi, lo), entry(b, b);
    }
    return out;
  }

 private:
  // The supernode of each column of L, each supernode's parent in the elimination tree (-1 for
  // a root) and the inverse of the fill-reducing permutation.
  void IndexSupernodes() {
    const cholmod_factor& l = sparse_->factor();
    if (!l.is_super || l.itype != CHOLMOD_INT || l.xtype != CHOLMOD_REAL) return;
    const int n = static_cast<int>(l.n), nsuper = static_cast<int>(l.nsuper);
    const auto [super, pi, px, ls, lx] = ArraysOf(l);
    const int* perm = static_cast<const int*>(l.Perm);
    column_super_.resize(n);
    for (int s = 0; s < nsuper; ++s) std::fill(&column_super_[super[s]], &column_super_[super[s + 1]], s);
    parent_.assign(nsuper, -1);
    for (int s = 0; s < nsuper; ++s) {
      const int ncols = super[s + 1] - super[s];
      if (pi[s + 1] - pi[s] > ncols) parent_[s] = column_super_[ls[pi[s] + ncols]];
    }
    std::vector<int> column_of(n);  // CHOLMOD's own permutation (the identity, as analysed), inverted
    for (int k = 0; k < n; ++k) column_of[perm[k]] = k;
    permuted_.resize(n);
    for (int r = 0; r < n; ++r) permuted_[r] = column_of[Ordered(r)];
    // The first supernode of each subtree; the tree is postordered (CHOLMOD's default) when every
    // subtree is the range first..itself.
    first_descendant_.resize(nsuper);
    std::vector<int> size(nsuper, 1);
    for (int s = 0; s < nsuper; ++s) first_descendant_[s] = s;
    for (int s = 0; s < nsuper; ++s) {
      if (parent_[s] < 0) continue;
      first_descendant_[parent_[s]] = std::min(first_descendant_[parent_[s]], first_descendant_[s]);
      size[parent_[s]] += size[s];
    }
    postordered_ = true;
    for (int s = 0; s < nsuper; ++s) postordered_ = postordered_ && size[s] == s - first_descendant_[s] + 1;
  }

  // The numeric factorisation of matrix_, with the analysis made.
  bool Numeric() {
    FactorizeOnThisThreadOnly();
    sparse_->factorize(matrix_);
    if (sparse_->info() != Eigen::Success) return false;
    IndexSupernodes();
    return true;
  }
  // The row of the ordered matrix that holds row `r` of the information in the landmarks' order,
  // and back.
  int Ordered(int r) const { return 2 * position_[r / 2] + r % 2; }
  int Original(int r) const { return 2 * order_[r / 2] + r % 2; }

  Eigen::MatrixXd dense_;  // L of a small window (lower triangle)
  std::unique_ptr<SupernodalLLT> sparse_;
  std::vector<int> order_, position_;  // of the landmarks, in a sparse factor
  Eigen::SparseMatrix<double> matrix_;  // the information factorised (sparse), ordered lower triangle
  bool ok_ = false;
  std::vector<int> column_super_, parent_, permuted_, first_descendant_;
  bool postordered_ = false;
};

namespace {

// Information of a positive semi-definite `info` on the entries `keep` once the others are
// eliminated: keep-keep - keep-other other-other^+ other-keep (the pseudo-inverse: a factor may
// carry no information in some directions of the landmarks it eliminates).
Eigen::MatrixXd SchurComplement(const Eigen::MatrixXd& info, const std::vector<int>& keep,
                                const std::vector<int>& other) {
  const int k = static_cast<int>(keep.size()), o = static_cast<int>(other.size());
  // Gathered column by column, as `info` is stored (a crossing factor spans up to a few hundred
  // unknowns).
  Eigen::MatrixXd kk(k, k), ok(o, k), oo(o, o);
  for (int b = 0; b < k; ++b) {
    const double* column = info.col(keep[b]).data();
    for (int a = 0; a < k; ++a) kk(a, b) = column[keep[a]];
    for (int a = 0; a < o; ++a) ok(a, b) = column[other[a]];
  }
  for (int b = 0; b < o; ++b) {
    const double* column = info.col(other[b]).data();
    for (int a = 0; a < o; ++a) oo(a, b) = column[other[a]];
  }
  // oo = P L L^T P^T, pivots largest first (LAPACK's pivoted Cholesky). Half of the factors leaving
  // a city window carry no information in some directions of the landmarks they eliminate: the
  // pivots left at or below the floor are those directions, along which ok has no component (info
  // is positive semi-definite), so stopping there gives the pseudo-inverse's Schur complement,
  // kk - Y^T Y with Y = L^-1 P^T ok over the pivots taken.
  const double floor = 1e-12 * std::max(1.0, o > 0 ? oo.diagonal().maxCoeff() : 0.0);
  std::vector<int> pivot;
  const int rank = PivotedCholeskyInPlace(oo, floor, &pivot);
  Eigen::MatrixXd y(rank, k);
  for (int i = 0; i < rank; ++i) y.row(i) = ok.row(pivot[i]);
  SolveLowerInPlace(oo.topLeftCorner(rank, rank), y);
  Eigen::MatrixXd schur = kk;
  AddGramLower(y, schur, -1.0);
  return schur.selfadjointView<Eigen::Lower>();
}

}  // namespace

const char* CovarianceBoundName(CovarianceBound bound) {
  switch (bound) {
    case CovarianceBound::kExact:
      return "exact";
    case CovarianceBound::kConservative:
      return "conservative";
    case CovarianceBound::kMayBeNarrower:
      return "may_be_narrower";
  }
  return "unknown";
}

absl::Status MapWindowOptions::Validate() const {
  if (hops < 0) return absl::InvalidArgumentError(absl::StrCat("window hops: must be >= 0, got ", hops));
  return absl::OkStatus();
}

absl::Status RemovedWhileRead(std::string_view what, int64_t id) {
  return absl::AbortedError(
      absl::StrCat(std::string(what), " ", id, ": removed while the map was read (a change committed meanwhile)"));
}

absl::StatusOr<Landmark> LandmarkStillThere(const MapReaderInterface& map, LandmarkId id) {
  const Landmark* record = map.FindLandmark(id);
  if (record == nullptr) return RemovedWhileRead("landmark", id);
  return *record;
}

absl::StatusOr<MapWindow> MapWindow::Build(const MapReaderInterface& map, const std::vector<LandmarkId>& seeds,
                                           const MapWindowOptions& options) {
  if (absl::Status s = options.Validate(); !s.ok()) return s;
  MapWindow w;
  // Breadth-first over the links, level by level.
  std::vector<LandmarkId> frontier;
  w.index_.reserve(seeds.size());
  for (LandmarkId id : seeds) {
    if (map.FindLandmark(id) == nullptr) return absl::NotFoundError(absl::StrCat("landmark ", id, ": not in the map"));
    if (w.index_.emplace(id, static_cast<int>(w.ids_.size())).second) {
      w.ids_.push_back(id);
      frontier.push_back(id);
    }
  }
  std::vector<LandmarkId> linked;
  for (int hop = 0; !frontier.empty() && (options.hops == 0 || hop < options.hops); ++hop) {
    std::vector<LandmarkId> next;
    for (LandmarkId id : frontier) {
      linked.clear();
      map.AppendLinked(id, &linked);
      for (LandmarkId other : linked) {
        if (w.index_.emplace(other, static_cast<int>(w.ids_.size())).second) {
          w.ids_.push_back(other);
          next.push_back(other);
        }
      }
    }
    frontier = std::move(next);
  }

  // The window's information, with the landmarks outside held at their estimate.
  const int n = static_cast<int>(w.ids_.size());
  if (n == 0) return w;
  // The right-hand side only for an estimate: a landmark's offset is a geodesic computation, and a
  // covariance read visits every link that leaves the window.
  UpperBlocks blocks(n);
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(options.estimate ? 2 * n : 0);
  std::vector<LandmarkId> edge;  // window landmarks linked to the outside
  // The estimates of the landmarks outside that the window's links reach, each computed once (a
  // geodesic computation; a landmark outside is linked to many inside).
  absl::flat_hash_map<LandmarkId, Eigen::Vector2d> outside_offsets;
  std::optional<LandmarkId> missing;  // an outside landmark linked but not found
  // The factors behind the links that leave the window, counted over those links (each link's
  // block counts the factors on both its landmarks, folded ones included; a block of the stored
  // base counts at least 1): compared below with what the kept factors account for.
  int64_t leaving_link_factors = 0;
  for (int i = 0; i < n; ++i) {
    const LandmarkId a = w.ids_[i];
    if (options.estimate) rhs.segment<2>(2 * i) = map.InformationVector(a);
    bool on_edge = false;
    const InformationBlock diagonal = map.VisitRow(a, [&](LandmarkId b, const InformationBlock& block) {
      const int j = w.index(b);
      if (j > i) {
        blocks.AddAbove(i, j, block.value);  // the block (a, b)
      } else if (j < 0) {
        on_edge = true;
        leaving_link_factors += block.factors;
        if (!options.estimate) return;
        auto [it, inserted] = outside_offsets.try_emplace(b);
        if (inserted) {
          const Landmark* outside = map.FindLandmark(b);
          if (outside == nullptr) {
            missing = b;
            return;
          }
          it->second = outside->Offset();
        }
        rhs.segment<2>(2 * i) -= block.value * it->second;
      }
    });
    blocks.AddDiagonal(i, diagonal.value);
    if (missing) return RemovedWhileRead("landmark", *missing);
    if (on_edge) edge.push_back(a);
  }
  w.closed_ = edge.empty();
  std::shared_ptr<Factor> mean_llt;
  if (options.estimate || w.closed_) {
    // The information with the landmarks outside held (a covariance read of an open window needs
    // only the conservative one below).
    mean_llt = std::make_shared<Factor>(blocks);
    if (mean_llt->info() != Eigen::Success) {
      return absl::FailedPreconditionError(
          absl::StrCat("map information over ", n, " landmarks is not positive definite"));
    }
    if (w.closed_) w.covariance_factor_ = mean_llt;
    if (options.estimate) {
      w.offsets_ = mean_llt->solve(rhs).col(0);
      if (!w.offsets_.allFinite()) return absl::InternalError("map estimate is not finite");
    }
  }
  if (w.closed_) return w;

  // Conservative covariance: every factor that reaches outside enters through its marginal on the
  // window instead of its conditional. They are found by their landmarks alone: the information of
  // the others is not needed (and a MapReadRecorder copies what it hands out).
  std::unordered_set<int64_t> crossing, checked;
  std::vector<int64_t> factor_ids;
  std::vector<LandmarkId> factor_landmarks;
  int64_t kept_leaving_links = 0;  // the links leaving the window that the kept factors make
  for (LandmarkId a : edge) {
    factor_ids.clear();
    map.AppendFactorIds(a, &factor_ids);
    for (int64_t id : factor_ids) {
      if (!checked.insert(id).second) continue;
      factor_landmarks.clear();
      if (!map.AppendFactorLandmarks(id, &factor_landmarks)) return RemovedWhileRead("map factor", id);
      const int64_t outside = std::count_if(factor_landmarks.begin(), factor_landmarks.end(),
                                            [&](LandmarkId l) { return w.index(l) < 0; });
      if (outside > 0) {
        crossing.insert(id);
        kept_leaving_links += outside * (static_cast<int64_t>(factor_landmarks.size()) - outside);
      }
    }
  }
  // Every factor on a leaving link is a kept one unless the map's base (folded factors, which the
  // window holds) has a share in one of them.
  w.bound_ = kept_leaving_links == leaving_link_factors ? CovarianceBound::kConservative
                                                        : CovarianceBound::kMayBeNarrower;
  bool pattern_grew = false;
  for (int64_t id : crossing) {
    const MapFactor* found = map.FindFactor(id);
    if (found == nullptr) return RemovedWhileRead("map factor", id);
    const MapFactor& f = *found;
    std::vector<int> keep, other, keep_index;
    for (size_t k = 0; k < f.landmarks.size(); ++k) {
      const int j = w.index(f.landmarks[k]);
      for (int c = 0; c < 2; ++c) (j >= 0 ? keep : other).push_back(static_cast<int>(2 * k) + c);
      if (j >= 0) keep_index.push_back(j);
    }
    const Eigen::MatrixXd schur = SchurComplement(f.information, keep, other);
    for (size_t a = 0; a < keep_index.size(); ++a) {
      for (size_t b = 0; b < keep_index.size(); ++b) {
        if (keep_index[a] > keep_index[b]) continue;  // the upper triangle
        const Eigen::Matrix2d conditional = f.information.block<2, 2>(keep[2 * a], keep[2 * b]);
        pattern_grew |= blocks.Add(keep_index[a], keep_index[b], schur.block<2, 2>(2 * a, 2 * b) - conditional);
      }
    }
  }
  // The Schur complements change blocks between landmarks of one factor, which the map links: the
  // pattern is the held information's, whose analysis a window with an estimate reuses.
  if (mean_llt && !pattern_grew) {
    mean_llt->Refactorize(blocks);
    w.covariance_factor_ = std::move(mean_llt);
  } else {
    w.covariance_factor_ = std::make_shared<const Factor>(blocks);
  }
  if (w.covariance_factor_->info() != Eigen::Success) {
    return absl::FailedPreconditionError(
        absl::StrCat("map marginal information over ", n, " landmarks is not positive definite"));
  }
  return w;
}

int MapWindow::index(LandmarkId id) const {
  auto it = index_.find(id);
  return it == index_.end() ? -1 : it->second;
}

absl::StatusOr<Eigen::MatrixXd> MapWindow::CovarianceColumns(const std::vector<LandmarkId>& ids) const {
  const int n = static_cast<int>(ids_.size()), m = static_cast<int>(ids.size());
  if (m == 0) return Eigen::MatrixXd(2 * n, 0);
  Eigen::MatrixXd unit = Eigen::MatrixXd::Zero(2 * n, 2 * m);
  for (int k = 0; k < m; ++k) {
    const int at = index(ids[k]);
    if (at < 0) return absl::InvalidArgumentError(absl::StrCat("landmark ", ids[k], ": outside the window"));
    unit.block<2, 2>(2 * at, 2 * k).setIdentity();
  }
  Eigen::MatrixXd columns = covariance_factor_->solve(unit);
  if (!columns.allFinite()) return absl::InternalError("map covariance is not finite");
  return columns;
}

absl::StatusOr<Eigen::VectorXd> MapWindow::CovarianceTimes(const std::vector<LandmarkId>& ids,
                                                           const Eigen::VectorXd& v) const {
  const int n = static_cast<int>(ids_.size());
  if (v.size() != 2 * static_cast<int>(ids.size())) {
    return absl::InvalidArgumentError("covariance product: the vector needs 2 entries per landmark");
  }
  if (n == 0) return Eigen::VectorXd(0);
  Eigen::VectorXd rhs = Eigen::VectorXd::Zero(2 * n);
  for (size_t k = 0; k < ids.size(); ++k) {
    const int at = index(ids[k]);
    if (at < 0) return absl::InvalidArgumentError(absl::StrCat("landmark ", ids[k], ": outside the window"));
    rhs.segment<2>(2 * at) += v.segment<2>(2 * k);
  }
  Eigen::VectorXd product = covariance_factor_->solve(rhs);
  if (!product.allFinite()) return absl::InternalError("map covariance is not finite");
  return product;
}

absl::StatusOr<Eigen::MatrixXd> MapWindow::Covariance(const std::vector<LandmarkId>& ids) const {
  std::vector<int> rows;
  rows.reserve(2 * ids.size());
  for (LandmarkId id : ids) {
    const int at = index(id);
    if (at < 0) return absl::InvalidArgumentError(absl::StrCat("landmark ", id, ": outside the window"));
    rows.push_back(2 * at);
    rows.push_back(2 * at + 1);
  }
  if (rows.empty()) return Eigen::MatrixXd(0, 0);
  Eigen::MatrixXd cov = covariance_factor_->InverseBlock(rows);
  if (!cov.allFinite()) return absl::InternalError("map covariance is not finite");
  return cov;
}

absl::StatusOr<Eigen::MatrixXd> MapWindow::FullCovariance() const {
  if (covariance_factor_ == nullptr) return Eigen::MatrixXd(0, 0);  // an empty window
  absl::StatusOr<Eigen::MatrixXd> cov = covariance_factor_->DenseInverse();
  if (cov.ok() && !cov->allFinite()) return absl::InternalError("map covariance is not finite");
  return cov;
}

std::vector<Eigen::Matrix2d> MapWindow::Marginals() const {
  if (ids_.empty()) return {};
  return covariance_factor_->InverseDiagonalBlocks();
}

absl::StatusOr<Eigen::MatrixXd> JointCovariance(const MapReaderInterface& map, const std::vector<LandmarkId>& ids,
                                                const MapWindowOptions& options, CovarianceBound* bound) {
  MapWindowOptions covariance_only = options;
  covariance_only.estimate = false;
  absl::StatusOr<MapWindow> window = MapWindow::Build(map, ids, covariance_only);
  if (!window.ok()) return window.status();
  if (bound != nullptr) *bound = window->covariance_bound();
  return window->Covariance(ids);
}

}  // namespace crowdmap
