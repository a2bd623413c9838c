#!/usr/bin/python3
"""Splits the joint NEES of maps of the same scenario built from different noise draws (seeds)
into what their mean error explains (a bias: the same on every draw) and their scatter around it.

  for s in 1 2 3 4 5 6 7 8 9 10; do
    build/client/mapsim experiment --landmarks 50 --passages 1024 --seed $s --out out/w$s --quiet
  done
  scripts/map-bias.py out/w1 out/w2 ... out/w10

Each directory is an `experiment` output (landmarks.csv, cross_covariances.csv). With E the
seeds' stacked errors (2 rows per landmark), e their mean over the seeds and S the maps' mean
joint covariance, m seeds and 2N degrees of freedom:
  own joint NEES    mean over seeds of e_s^T S_s^-1 e_s / 2N
  bias part         m e^T S^-1 e / 2N: about 1 without a bias (e then has covariance S / m)
  scatter part      mean of (e_s - e)^T S^-1 (e_s - e) / 2N, times m / (m - 1): about 1 when
                    the covariance describes the error's random part
and both again over the quarters of S's eigen-directions, smallest variance first.

Debian: python3-numpy (run with /usr/bin/python3)."""
import sys

import numpy as np


def load(directory):
    lm = np.genfromtxt(f"{directory}/landmarks.csv", delimiter=",", names=True)
    ids = lm["landmark"].astype(int)
    n = len(ids)
    index = {landmark: k for k, landmark in enumerate(ids)}
    errors = np.zeros(2 * n)
    cov = np.zeros((2 * n, 2 * n))
    for k in range(n):
        errors[2 * k : 2 * k + 2] = lm["east_err_m"][k], lm["north_err_m"][k]
        cov[2 * k : 2 * k + 2, 2 * k : 2 * k + 2] = [[lm["cov_ee_m2"][k], lm["cov_en_m2"][k]],
                                                    [lm["cov_en_m2"][k], lm["cov_nn_m2"][k]]]
    cross = np.genfromtxt(f"{directory}/cross_covariances.csv", delimiter=",", names=True)
    for row in np.atleast_1d(cross):
        a, b = index[int(row["landmark_a"])], index[int(row["landmark_b"])]
        block = np.array([[row["cov_ee_m2"], row["cov_en_m2"]], [row["cov_ne_m2"], row["cov_nn_m2"]]])
        cov[2 * a : 2 * a + 2, 2 * b : 2 * b + 2] = block
        cov[2 * b : 2 * b + 2, 2 * a : 2 * a + 2] = block.T
    return ids, errors, cov


def main():
    if len(sys.argv) < 3:
        sys.exit(__doc__)
    runs = [load(d) for d in sys.argv[1:]]
    if any(not np.array_equal(r[0], runs[0][0]) for r in runs):
        sys.exit("the maps do not hold the same landmarks")
    errors = np.array([r[1] for r in runs])
    m, dof = errors.shape
    cov = np.mean([r[2] for r in runs], axis=0)
    own = np.mean([e @ np.linalg.solve(c, e) for _, e, c in runs]) / dof
    mean = errors.mean(axis=0)
    variances, directions = np.linalg.eigh(cov)
    bias = m * (directions.T @ mean) ** 2 / variances
    scatter = np.mean([(directions.T @ (e - mean)) ** 2 / variances for e in errors], axis=0) * m / (m - 1)
    print(f"seeds={m} dof={dof} own_joint_nees={own:.2f} bias_part={bias.mean():.2f} scatter_part={scatter.mean():.2f}")
    quarter = dof // 4
    for q in range(4):
        part = slice(q * quarter, (q + 1) * quarter if q < 3 else dof)
        print(f"  directions {q + 1}/4 (smallest variance first): bias {bias[part].mean():.2f} scatter {scatter[part].mean():.2f}")
    print(f"mean error over the seeds: east {mean[0::2].mean():+.4f} m, north {mean[1::2].mean():+.4f} m on average, "
          f"rms {np.sqrt((mean ** 2).mean()):.4f} m; rms error of one map {np.sqrt((errors ** 2).mean()):.4f} m")


if __name__ == "__main__":
    main()
