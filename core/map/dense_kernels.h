#ifndef CROWDMAP_CORE_MAP_DENSE_KERNELS_H_
#define CROWDMAP_CORE_MAP_DENSE_KERNELS_H_

// The dense kernels of the covariance reads and of localisation, on LAPACK and BLAS: the system's
// (scripts/setup.sh installs OpenBLAS, whose kernels are picked for the CPU at run time) run
// these 2.5 to 5 times faster than Eigen's, which are compiled for the baseline x86-64. Explicit
// calls, not EIGEN_USE_BLAS: that would change Eigen's code in this project's objects only, and
// the same Eigen function would then run different code in the service and in Ceres.
// Column-major matrices, lower triangles; blocks of a larger matrix are fine (outer stride).

#include <vector>

#include <Eigen/Core>

namespace crowdmap {

using MatrixRef = Eigen::Ref<Eigen::MatrixXd, 0, Eigen::OuterStride<>>;
using ConstMatrixRef = Eigen::Ref<const Eigen::MatrixXd, 0, Eigen::OuterStride<>>;

// A = L L^T for a symmetric A given by its lower triangle: L replaces it (the strict upper
// triangle is not read or written). False when A is not positive definite.
bool CholeskyInPlace(MatrixRef a);

// Cholesky with diagonal pivoting of a positive semi-definite A given by its lower triangle:
// P^T A P = L L^T, the pivots taken largest first until the largest left is at most `tol`. Returns
// the rank r (the pivots taken); L's first r columns replace A's lower triangle (what lies beyond
// them is undefined), and (*pivot)[i] is the row of A taken i-th (0-based).
int PivotedCholeskyInPlace(MatrixRef a, double tol, std::vector<int>* pivot);

// A^-1 from CholeskyInPlace's L, in its place: the whole symmetric matrix.
void InverseFromCholeskyInPlace(MatrixRef l);

// L^-1 for a lower-triangular L, in its place (the strict upper triangle is not read or written).
void LowerInverseInPlace(MatrixRef l);

// X := L^-1 X for a lower-triangular L (its strict upper triangle is not read).
void SolveLowerInPlace(ConstMatrixRef l, MatrixRef x);

// The lower triangle of C := C + scale X^T X (the upper is not written).
void AddGramLower(ConstMatrixRef x, MatrixRef c, double scale = 1.0);

// C := A B (C sized to fit).
void Multiply(ConstMatrixRef a, ConstMatrixRef b, Eigen::MatrixXd* c);

// The eigenvalues of a symmetric A given by its lower triangle, in increasing order, and its
// eigenvectors in their place in A, column k for eigenvalue k (LAPACK's dsyevd). False when the
// iteration did not converge (A is then undefined).
bool SymmetricEigenInPlace(MatrixRef a, Eigen::VectorXd* values);

// A symmetric A (its lower triangle read) whose negative eigenvalues all lie within `tolerance` of
// zero, replaced by its positive semi-definite part: V max(L, 0) V^T, whole. False, with A left as
// it was, when an eigenvalue lies below -tolerance or the decomposition fails.
bool ClipSmallNegativeEigenvalues(Eigen::MatrixXd* a, double tolerance);

}  // namespace crowdmap

#endif  // CROWDMAP_CORE_MAP_DENSE_KERNELS_H_
