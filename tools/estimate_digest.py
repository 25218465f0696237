"""A digest of every estimate a benchmark makes: the check that a refactor changed no result.

    .venv/bin/python tools/estimate_digest.py --out before.npz -- \
        benchmarks/bench_align.py --poses 4
    .venv/bin/python tools/estimate_digest.py --compare before.npz after.npz

Runs the benchmark as ``__main__`` with ``align.estimate`` wrapped so that every call's status,
pose (x, y, z, roll, tilt, yaw), covariance and the diagnostics' numbers are kept in call
order, then prints one SHA-256 over them. ``--compare`` lists every estimate that differs and
the largest relative difference: a refactor that truly must change floating-point order shows
there, below 1e-9 relative, or it changed a result.
"""

from __future__ import annotations

import argparse
import hashlib
import runpy
import sys
from pathlib import Path

import numpy as np


def _row(est) -> tuple[str, np.ndarray]:
    pose = est.pose
    values = np.full(6 + 36, np.nan)
    if pose is not None:
        values[:6] = [pose.x, pose.y, pose.z, pose.roll, pose.tilt, pose.yaw]
    if est.covariance is not None:
        values[6:] = np.asarray(est.covariance, dtype=float).ravel()
    return str(est.status), values


def record(out: Path, argv: list[str]) -> None:
    import align

    statuses: list[str] = []
    methods: list[str] = []
    rows: list[np.ndarray] = []
    inner = align.estimate

    def estimate(*args, **kwargs):
        est = inner(*args, **kwargs)
        status, values = _row(est)
        statuses.append(status)
        methods.append(est.method)
        rows.append(values)
        return est

    align.estimate = estimate
    sys.argv = argv
    try:
        runpy.run_path(argv[0], run_name="__main__")
    except SystemExit as stop:
        if stop.code not in (0, None):
            raise
    finally:
        values = np.array(rows).reshape(-1, 42)
        np.savez(out, status=np.array(statuses), method=np.array(methods), values=values)
        print(f"digest: {len(rows)} estimates, sha256 {digest(statuses, values)}  -> {out}")


def digest(statuses, values: np.ndarray) -> str:
    h = hashlib.sha256()
    h.update("\n".join(statuses).encode())
    h.update(np.ascontiguousarray(values).tobytes())
    return h.hexdigest()


def compare(a: Path, b: Path) -> int:
    da, db = np.load(a), np.load(b)
    if len(da["status"]) != len(db["status"]):
        print(f"different counts: {len(da['status'])} vs {len(db['status'])}")
        return 1
    # Open3D's ICP sums in parallel threads: the same scan estimated twice in one process can
    # differ by 1e-16 (relative), so its estimates are compared apart
    method = db["method"] if "method" in db.files else da["method"]
    bad = 0
    worst = 0.0
    icp = 0
    for i, (sa, sb) in enumerate(zip(da["status"], db["status"], strict=True)):
        va, vb = da["values"][i], db["values"][i]
        same_nan = np.isnan(va) == np.isnan(vb)
        scale = np.maximum(np.abs(va), np.abs(vb))
        scale[scale == 0] = 1.0
        rel = np.where(np.isnan(va) | np.isnan(vb), 0.0, np.abs(va - vb) / scale)
        if sa != sb or not same_nan.all() or rel.max() > 0:
            if method[i] == "icp" and sa == sb and same_nan.all() and rel.max() < 1e-9:
                icp += 1
                continue
            bad += 1
            worst = max(worst, float(rel.max()))
            print(f"estimate {i}: {sa} vs {sb}, largest relative difference {rel.max():.3g}")
    keep = method != "icp"
    for name, d in ((a, da), (b, db)):
        print(f"{name}: {digest(d['status'], d['values'])}, without icp "
              f"{digest(d['status'][keep], d['values'][keep])}")
    print(f"{bad} of {len(da['status'])} estimates differ; largest relative difference {worst:.3g}"
          f" ({icp} icp estimates within 1e-9, Open3D's own scatter)")
    return 1 if bad else 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path)
    ap.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"))
    ap.add_argument("bench", nargs=argparse.REMAINDER, help="-- SCRIPT [ARGS]")
    args = ap.parse_args()
    if args.compare:
        return compare(*args.compare)
    argv = [a for a in args.bench if a != "--"] if args.bench else []
    if not argv or args.out is None:
        ap.error("give --out FILE -- SCRIPT [ARGS], or --compare A B")
    sys.path.insert(0, str(Path(argv[0]).resolve().parent))
    record(args.out, argv)
    return 0


if __name__ == "__main__":
    sys.exit(main())
