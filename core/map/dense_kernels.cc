#include "core/map/dense_kernels.h"

#include <algorithm>

#include "core/map/sparse_threads.h"

extern "C" {
void dpotrf_(const char* uplo, const int* n, double* a, const int* lda, int* info);
void dpstrf_(const char* uplo, const int* n, double* a, const int* lda, int* piv, int* rank, const double* tol,
             double* work, int* info);
void dpotri_(const char* uplo, const int* n, double* a, const int* lda, int* info);
void dtrtri_(const char* uplo, const char* diag, const int* n, double* a, const int* lda, int* info);
void dtrsm_(const char* side, const char* uplo, const char* transa, const char* diag, const int* m, const int* n,
            const double* alpha, const double* a, const int* lda, double* b, const int* ldb);
void dgemm_(const char* transa, const char* transb, const int* m, const int* n, const int* k, const double* alpha,
            const double* a, const int* lda, const double* b, const int* ldb, const double* beta, double* c,
            const int* ldc);
void dsyrk_(const char* uplo, const char* trans, const int* n, const int* k, const double* alpha, const double* a,
            const int* lda, const double* beta, double* c, const int* ldc);
void dsyevd_(const char* jobz, const char* uplo, const int* n, double* a, const int* lda, double* w, double* work,
             const int* lwork, int* iwork, const int* liwork, int* info);
}

namespace crowdmap {
namespace {

// A leading dimension BLAS accepts (at least 1, also for an empty matrix).
int Leading(Eigen::Index stride) { return stride > 0 ? static_cast<int>(stride) : 1; }

}  // namespace

bool CholeskyInPlace(MatrixRef a) {
  KeepBlasOnTheCallingThread();
  const int n = static_cast<int>(a.rows()), lda = Leading(a.outerStride());
  if (n == 0) return true;
  int info = 0;
  dpotrf_("L", &n, a.data(), &lda, &info);
  return info == 0;
}

int PivotedCholeskyInPlace(MatrixRef a, double tol, std::vector<int>* pivot) {
  KeepBlasOnTheCallingThread();
  const int n = static_cast<int>(a.rows()), lda = Leading(a.outerStride());
  pivot->resize(n);
  if (n == 0) return 0;
  std::vector<double> work(2 * static_cast<size_t>(n));
  int rank = 0, info = 0;
  dpstrf_("L", &n, a.data(), &lda, pivot->data(), &rank, &tol, work.data(), &info);
  if (info < 0) return 0;  // an illegal argument: not reached with a square matrix
  for (int& p : *pivot) --p;  // LAPACK counts from 1
  return rank;
}

void InverseFromCholeskyInPlace(MatrixRef l) {
  KeepBlasOnTheCallingThread();
  const int n = static_cast<int>(l.rows()), lda = Leading(l.outerStride());
  if (n == 0) return;
  int info = 0;
  dpotri_("L", &n, l.data(), &lda, &info);  // info != 0 only for a zero on L's diagonal
  l.triangularView<Eigen::StrictlyUpper>() = l.transpose();
}

void LowerInverseInPlace(MatrixRef l) {
  KeepBlasOnTheCallingThread();
  const int n = static_cast<int>(l.rows()), lda = Leading(l.outerStride());
  if (n == 0) return;
  int info = 0;
  dtrtri_("L", "N", &n, l.data(), &lda, &info);
}

void SolveLowerInPlace(ConstMatrixRef l, MatrixRef x) {
  KeepBlasOnTheCallingThread();
  const int m = static_cast<int>(x.rows()), n = static_cast<int>(x.cols());
  if (m == 0 || n == 0) return;
  const int lda = Leading(l.outerStride()), ldb = Leading(x.outerStride());
  const double one = 1.0;
  dtrsm_("L", "L", "N", "N", &m, &n, &one, l.data(), &lda, x.data(), &ldb);
}

void AddGramLower(ConstMatrixRef x, MatrixRef c, double scale) {
  KeepBlasOnTheCallingThread();
  const int n = static_cast<int>(x.cols()), k = static_cast<int>(x.rows());
  if (n == 0 || k == 0) return;
  const int lda = Leading(x.outerStride()), ldc = Leading(c.outerStride());
  const double one = 1.0;
  dsyrk_("L", "T", &n, &k, &scale, x.data(), &lda, &one, c.data(), &ldc);
}

void Multiply(ConstMatrixRef a, ConstMatrixRef b, Eigen::MatrixXd* c) {
  KeepBlasOnTheCallingThread();
  const int m = static_cast<int>(a.rows()), n = static_cast<int>(b.cols()), k = static_cast<int>(a.cols());
  c->resize(m, n);
  if (m == 0 || n == 0) return;
  if (k == 0) {
    c->setZero();
    return;
  }
  const int lda = Leading(a.outerStride()), ldb = Leading(b.outerStride()), ldc = Leading(c->outerStride());
  const double one = 1.0, zero = 0.0;
  dgemm_("N", "N", &m, &n, &k, &one, a.data(), &lda, b.data(), &ldb, &zero, c->data(), &ldc);
}

bool SymmetricEigenInPlace(MatrixRef a, Eigen::VectorXd* values) {
  KeepBlasOnTheCallingThread();
  const int n = static_cast<int>(a.rows()), lda = Leading(a.outerStride());
  values->resize(n);
  if (n == 0) return true;
  // The workspace sizes LAPACK asks for, then the decomposition.
  double work_size = 0.0;
  int iwork_size = 0, query = -1, info = 0;
  dsyevd_("V", "L", &n, a.data(), &lda, values->data(), &work_size, &query, &iwork_size, &query, &info);
  if (info != 0) return false;
  const int lwork = static_cast<int>(work_size), liwork = iwork_size;
  std::vector<double> work(std::max(1, lwork));
  std::vector<int> iwork(std::max(1, liwork));
  dsyevd_("V", "L", &n, a.data(), &lda, values->data(), work.data(), &lwork, iwork.data(), &liwork, &info);
  return info == 0;
}

bool ClipSmallNegativeEigenvalues(Eigen::MatrixXd* a, double tolerance) {
  Eigen::MatrixXd vectors = *a;
  Eigen::VectorXd values;
  if (!SymmetricEigenInPlace(vectors, &values)) return false;
  if (values.size() == 0) return true;
  if (values(0) < -tolerance) return false;
  // V max(L, 0) V^T = W^T W with W = sqrt(max(L, 0)) V^T.
  const Eigen::MatrixXd w = values.cwiseMax(0.0).cwiseSqrt().asDiagonal() * vectors.transpose();
  a->setZero();
  AddGramLower(w, *a);
  *a = a->selfadjointView<Eigen::Lower>();
  return true;
}

}  // namespace crowdmap
