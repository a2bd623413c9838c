#include "core/map/selected_inverse.h"

#include <algorithm>

namespace crowdmap {

SelectedInverse::SelectedInverse(const Eigen::SimplicialLLT<Eigen::SparseMatrix<double>>& factor)
    : perm_(factor.permutationP().indices()), l_(factor.matrixL()) {
  l_.makeCompressed();
  const int n = static_cast<int>(l_.cols());
  const int* outer = l_.outerIndexPtr();
  const int* inner = l_.innerIndexPtr();
  const double* lv = l_.valuePtr();
  values_.assign(l_.nonZeros(), 0.0);
  // Entry (row, col), row >= col, in column col (row indices sorted, the diagonal first).
  auto at = [&](int row, int col) -> double {
    const int* it = std::lower_bound(inner + outer[col], inner + outer[col + 1], row);
    return values_[it - inner];
  };
  // L^T Sigma = L^-1, columns from the last: for i >= j on the pattern of column j,
  //   Sigma_ij = (delta_ij / L_jj - sum_{k > j} L_kj Sigma_ki) / L_jj,
  // where every Sigma_ki needed lies on the pattern (a property of Cholesky fill).
  for (int j = n - 1; j >= 0; --j) {
    const int first = outer[j], last = outer[j + 1];
    const double ljj = lv[first];
    for (int q = last - 1; q >= first; --q) {
      const int i = inner[q];
      double s = i == j ? 1.0 / ljj : 0.0;
      for (int r = first + 1; r < last; ++r) {
        const int k = inner[r];
        s -= lv[r] * (k >= i ? at(k, i) : at(i, k));
      }
      values_[q] = s / ljj;
    }
  }
}

double SelectedInverse::operator()(int i, int j) const {
  int a = perm_[i], b = perm_[j];
  if (a < b) std::swap(a, b);
  const int* begin = l_.innerIndexPtr() + l_.outerIndexPtr()[b];
  const int* end = l_.innerIndexPtr() + l_.outerIndexPtr()[b + 1];
  const int* it = std::lower_bound(begin, end, a);
  return it != end && *it == a ? values_[it - l_.innerIndexPtr()] : 0.0;
}

Eigen::MatrixXd SolveManyColumns(const Eigen::SimplicialLLT<Eigen::SparseMatrix<double>>& factor,
                                 const Eigen::MatrixXd& b) {
  // P A P^T = L L^T, each column of L its diagonal first.
  const Eigen::SparseMatrix<double>& l = factor.matrixL().nestedExpression();
  const int n = static_cast<int>(l.cols());
  if (!l.isCompressed() || b.rows() != n) return factor.solve(b);
  const int* outer = l.outerIndexPtr();
  const int* inner = l.innerIndexPtr();
  const double* lv = l.valuePtr();
  for (int j = 0; j < n; ++j) {
    if (outer[j] == outer[j + 1] || inner[outer[j]] != j) return factor.solve(b);
  }
  const Eigen::VectorXi& perm = factor.permutationP().indices();
  const auto at = [&](int i) { return perm.size() > 0 ? perm[i] : i; };
  Eigen::Matrix<double, Eigen::Dynamic, Eigen::Dynamic, Eigen::RowMajor> x(n, b.cols());
  for (int i = 0; i < n; ++i) x.row(at(i)) = b.row(i);
  for (int j = 0; j < n; ++j) {  // L y = P b
    x.row(j) /= lv[outer[j]];
    for (int q = outer[j] + 1; q < outer[j + 1]; ++q) x.row(inner[q]) -= lv[q] * x.row(j);
  }
  for (int j = n - 1; j >= 0; --j) {  // L^T z = y
    for (int q = outer[j] + 1; q < outer[j + 1]; ++q) x.row(j) -= lv[q] * x.row(inner[q]);
    x.row(j) /= lv[outer[j]];
  }
  Eigen::MatrixXd out(n, b.cols());
  for (int i = 0; i < n; ++i) out.row(i) = x.row(at(i));
  return out;
}

}  // namespace crowdmap
