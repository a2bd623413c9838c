#!/usr/bin/env python3
"""Checks deploy/ the way CI can without a cluster or a container runtime.

    scripts/check-deploy.py [PATH_TO_MAPD [OTHER_BINARIES...]]

- every JSON and YAML file parses; the Kubernetes manifest keeps one replica, a pinned image tag
  (never :latest), a headless Service named by the StatefulSet, a NetworkPolicy for mapd's pods;
- every metric the Grafana dashboard queries is one mapd exports (server/metrics.cc);
- the Dockerfile has a build and a runtime stage, and .dockerignore keeps builds, maps and .git out;
  its runtime stage installs OpenBLAS's pthread build, never the single-threaded one;
- with mapd: deploy/mapd.conf and the ConfigMap's mapd.conf are accepted by mapd itself, the
  runtime stage installs a package for every shared library mapd (and the other binaries given)
  needs (apt-cache, readelf), and
  `systemd-analyze verify` accepts the unit (pointing ExecStart at this mapd) when systemd-analyze
  is installed.
Prints one line per check; exits 1 when any fails. A check that cannot run here says "skipped".
"""
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile

import yaml

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
failures = []


def check(name, ok, detail=""):
    print(("ok      " if ok else "FAILED  ") + name + (": " + detail if detail else ""))
    if not ok:
        failures.append(name)


def skipped(name, why):
    print("skipped " + name + ": " + why)


def read(path):
    with open(os.path.join(ROOT, path)) as f:
        return f.read()


def kubernetes():
    docs = []
    for name in sorted(os.listdir(os.path.join(ROOT, "deploy/kubernetes"))):
        if name.endswith((".yaml", ".yml")):
            try:
                docs += [d for d in yaml.safe_load_all(read("deploy/kubernetes/" + name)) if d]
                check("yaml parses: deploy/kubernetes/" + name, True)
            except yaml.YAMLError as e:
                check("yaml parses: deploy/kubernetes/" + name, False, str(e))
    by_kind = {}
    for d in docs:
        by_kind.setdefault(d["kind"], []).append(d)
    sets = by_kind.get("StatefulSet", [])
    check("one StatefulSet", len(sets) == 1)
    if not sets:
        return by_kind
    sts = sets[0]
    check("StatefulSet replicas == 1 (one replica owns one SQLite map)", sts["spec"].get("replicas") == 1)
    for c in sts["spec"]["template"]["spec"]["containers"]:
        image = c["image"]
        tag = image.rsplit(":", 1)[1] if ":" in image.rsplit("/", 1)[-1] else ""
        check("image pinned: " + image, tag not in ("", "latest") or "@sha256:" in image)
    headless = [s for s in by_kind.get("Service", []) if s["spec"].get("clusterIP") == "None"]
    check("headless Service named by the StatefulSet",
          any(s["metadata"]["name"] == sts["spec"]["serviceName"] for s in headless))
    labels = sts["spec"]["template"]["metadata"]["labels"]
    policies = by_kind.get("NetworkPolicy", [])
    check("NetworkPolicy selects mapd's pods",
          any(all(labels.get(k) == v for k, v in p["spec"]["podSelector"].get("matchLabels", {}).items())
              for p in policies))
    return by_kind


def dashboard_metrics():
    exported = set(re.findall(r'"(mapd_[a-z_]+)"', read("server/metrics.cc")))
    for name in sorted(os.listdir(os.path.join(ROOT, "deploy/grafana"))):
        if not name.endswith(".json"):
            continue
        try:
            dashboard = json.loads(read("deploy/grafana/" + name))
        except json.JSONDecodeError as e:
            check("json parses: deploy/grafana/" + name, False, str(e))
            continue
        check("json parses: deploy/grafana/" + name, True)
        queried = set()
        for panel in dashboard["panels"]:
            for target in panel.get("targets", []):
                queried |= {re.sub(r"_(bucket|count|sum)$", "", m) for m in re.findall(r"mapd_[a-z_]+", target["expr"])}
        unknown = sorted(q for q in queried if q not in exported)
        check("dashboard queries only exported metrics", not unknown, ", ".join(unknown))


def docker():
    dockerfile = read("deploy/Dockerfile")
    stages = re.findall(r"^FROM\s+\S+(?:\s+AS\s+(\S+))?", dockerfile, re.M | re.I)
    check("Dockerfile has a build and a runtime stage", len(stages) >= 2)
    ignore = read(".dockerignore").split()
    check(".dockerignore keeps .git, builds and maps out", all(p in ignore for p in (".git", "build*/", "*.db")))
    runtime = dockerfile[dockerfile.lower().rfind("\nfrom "):]
    check("runtime stage installs OpenBLAS's pthread build, not the single-threaded one (mapd refuses it)",
          re.search(r"\blibopenblas0-pthread\b", runtime) and not re.search(r"\blibopenblas0-serial\b", runtime))
    return dockerfile


def with_mapd(mapd, others, by_kind, dockerfile):
    def accepts(name, text):
        with tempfile.NamedTemporaryFile("w", suffix=".conf") as f:
            f.write(text)
            f.flush()
            r = subprocess.run([mapd, "--config", f.name, "--version"], capture_output=True, text=True)
        check("mapd accepts " + name, r.returncode == 0, r.stderr.strip())

    accepts("deploy/mapd.conf", read("deploy/mapd.conf"))
    for cm in by_kind.get("ConfigMap", []):
        for key, text in cm.get("data", {}).items():
            if key.endswith(".conf"):
                accepts("ConfigMap " + cm["metadata"]["name"] + "/" + key, text)

    runtime = dockerfile[dockerfile.lower().rfind("\nfrom "):]
    if shutil.which("readelf") and shutil.which("dpkg") and shutil.which("apt-cache"):
        listed = set(re.findall(r"\b(lib[a-z0-9.+-]+)\b", runtime))
        depends = subprocess.run(["apt-cache", "depends", "--recurse", "--no-recommends", "--no-suggests",
                                  "--no-conflicts", "--no-breaks", "--no-replaces", "--no-enhances"] + sorted(listed),
                                 capture_output=True, text=True).stdout
        provided = listed | {line.strip().split(":", 1)[-1].strip().split(":")[0] for line in depends.splitlines()}
        needed = set()
        for binary in [mapd] + others:
            needed |= set(re.findall(r"\(NEEDED\)\s+Shared library: \[(.+?)\]", subprocess.run(
                ["readelf", "-d", binary], capture_output=True, text=True).stdout))
        missing = []
        for lib in sorted(needed):
            owner = subprocess.run(["dpkg", "-S", "*/" + lib], capture_output=True, text=True).stdout
            packages = {line.split(":")[0] for line in owner.splitlines() if line}
            if packages and not packages & provided:
                missing.append(lib + " (" + ",".join(sorted(packages)) + ")")
        check("runtime stage installs every library the binaries need", not missing, "; ".join(missing))
    else:
        skipped("runtime libraries", "readelf, dpkg or apt-cache not installed")

    if shutil.which("systemd-analyze"):
        with tempfile.TemporaryDirectory() as tmp:
            unit = os.path.join(tmp, "mapd.service")
            with open(unit, "w") as f:
                f.write(read("deploy/systemd/mapd.service").replace("/usr/local/bin/mapd", os.path.abspath(mapd)))
            r = subprocess.run(["systemd-analyze", "verify", "--man=no", unit], capture_output=True, text=True)
            # verify also reports on units outside ours (the host's own): keep the lines about ours.
            ours = [l for l in (r.stdout + r.stderr).splitlines() if "mapd.service" in l]
            check("systemd-analyze verify deploy/systemd/mapd.service", r.returncode == 0 and not ours, "; ".join(ours))
    else:
        skipped("systemd-analyze verify", "systemd-analyze not installed")


def main():
    by_kind = kubernetes()
    dashboard_metrics()
    dockerfile = docker()
    if len(sys.argv) > 1:
        with_mapd(sys.argv[1], sys.argv[2:], by_kind, dockerfile)
    else:
        skipped("checks with mapd", "no path to mapd given")
    print("deploy check: " + ("FAILED: " + ", ".join(failures) if failures else "all passed"))
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
