#!/usr/bin/python3
"""Splits `mapsim city` results into the early and the late district (--late-blocks-x).

Usage: scripts/city-districts.py OUT_DIR [OUT_DIR ...]

For each run folder (summary.json, landmarks.csv) prints, for the landmarks of the western part
(driven from the first passage) and of the eastern late district (driven only from
--late-from-passage on): how many are mapped, their mean and median error, and their NEES per
degree of freedom (mean of e^T Sigma^-1 e / 2 over the landmarks, Sigma each landmark's marginal).
Where the run computed the Cramer-Rao bound (landmarks.csv's crlb_ columns), also the district's
mean error over the bound's mean expected error, and the NEES per degree of freedom against the
bound's marginals (1 for an efficient unbiased map; the two districts of one run compared on the
same passages).
A landmark belongs to the late district when its true position lies east of the street that
bounds it, by more than a road half width and a kerb offset (15 m).
"""
import csv
import json
import os
import statistics
import sys


def split(run_dir):
    summary_path = os.path.join(run_dir, "summary.json")
    if not os.path.isfile(summary_path):
        raise SystemExit(f"{run_dir}: no summary.json (not a `mapsim city` output folder, or the run is not done)")
    with open(summary_path) as f:
        summary = json.load(f)
    late_blocks = summary.get("late_blocks_x", 0)
    if late_blocks <= 0:
        raise SystemExit(f"{run_dir}: not a run with a late district (late_blocks_x is 0)")
    boundary_m = (summary["blocks_x"] - late_blocks) * summary["block_m"] + 15.0
    districts = {"early": [], "late": []}
    with open(os.path.join(run_dir, "landmarks.csv")) as f:
        for row in csv.DictReader(f):
            east = float(row["true_east_m"])
            bound = (float(row["crlb_error_m"]), float(row["crlb_mahalanobis2"])) if row.get("crlb_error_m") else None
            districts["late" if east > boundary_m else "early"].append(
                (float(row["error_m"]), float(row["mahalanobis2"]), bound))
    return summary, districts


def main(argv):
    if len(argv) < 2 or argv[1] in ("-h", "--help"):
        print(__doc__.strip())
        return 0 if len(argv) >= 2 else 2
    print("run | district | landmarks | mean error (m) | median error (m) | NEES/dof | error / CRLB | NEES/dof against the CRLB")
    for run_dir in argv[1:]:
        summary, districts = split(run_dir)
        for name, rows in districts.items():
            if not rows:
                print(f"{run_dir} | {name} | 0 | | | | |")
                continue
            errors = [e for e, _, _ in rows]
            nees = statistics.fmean(m for _, m, _ in rows) / 2.0
            bounds = [b for _, _, b in rows if b is not None]
            against_bound = " | |"
            if len(bounds) == len(rows):
                against_bound = (f" | {statistics.fmean(errors) / statistics.fmean(b for b, _ in bounds):.3f}"
                                 f" | {statistics.fmean(m for _, m in bounds) / 2.0:.2f}")
            print(f"{run_dir} | {name} | {len(rows)} | {statistics.fmean(errors):.3f} | "
                  f"{statistics.median(errors):.3f} | {nees:.2f}{against_bound}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
