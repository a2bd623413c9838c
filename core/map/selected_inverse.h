#ifndef CROWDMAP_CORE_MAP_SELECTED_INVERSE_H_
#define CROWDMAP_CORE_MAP_SELECTED_INVERSE_H_

#include <vector>

#include <Eigen/SparseCholesky>
#include <Eigen/SparseCore>

namespace crowdmap {

// Entries of A^-1 on the pattern of the Cholesky factor of a sparse symmetric positive definite A
// (Takahashi's recursion): every (i, j) where A is non-zero, and its fill.
class SelectedInverse {
 public:
  explicit SelectedInverse(const Eigen::SimplicialLLT<Eigen::SparseMatrix<double>>& factor);
  // (A^-1)_ij; 0 off the factor's pattern (where the entry is not computed, not zero).
  double operator()(int i, int j) const;

 private:
  Eigen::VectorXi perm_;           // original index -> factor index
  Eigen::SparseMatrix<double> l_;  // lower Cholesky factor of the permuted matrix
  std::vector<double> values_;     // inverse entries on l_'s pattern
};

// A^-1 B for A factorised by `factor` and a dense B of many columns. Eigen's solve sweeps the
// factor once for each column of B; this sweeps it once, each entry of the factor updating a whole
// row of the right-hand sides at once (rows stored contiguously).
Eigen::MatrixXd SolveManyColumns(const Eigen::SimplicialLLT<Eigen::SparseMatrix<double>>& factor,
                                 const Eigen::MatrixXd& b);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MAP_SELECTED_INVERSE_H_
