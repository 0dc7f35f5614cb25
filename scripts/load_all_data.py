"""Try :func:`kinefuse.io.load` on every file and folder of a data tree; write or compare a summary.

Used to show that a reader change makes nothing that loaded stop loading::

    python scripts/load_all_data.py ../shared/data --out before.json     # on the old code
    python scripts/load_all_data.py ../shared/data --out after.json      # on the new code
    python scripts/load_all_data.py --diff before.json after.json

Each entry is ``ok`` with a short content summary (format, IMU keys and lengths, joint names,
durations) or ``error`` with the exception type and message. Licence and README files are skipped.
"""

from __future__ import annotations

import argparse
import json
import sys
import warnings
from pathlib import Path

import numpy as np

_SKIP_SUFFIXES = {".md", ".license"}


def _median_norm(a) -> float | None:
    if a is None:
        return None
    n = np.linalg.norm(np.asarray(a, dtype=float), axis=-1)
    n = n[np.isfinite(n)]
    return round(float(np.median(n)), 6) if n.size else None


def _summary(rec) -> dict:
    """Sizes, durations, names and a numeric fingerprint (median norms, availability)."""
    out = {"format": rec.metadata.get("format")}
    out["imu"] = {
        k: [
            len(s),
            round(float(s.t_s[-1] - s.t_s[0]), 4) if len(s) else 0.0,
            _median_norm(s.acc_m_s2),
            _median_norm(s.gyr_rad_s),
            _median_norm(s.q_world_from_sensor),
        ]
        for k, s in rec.imu.items()
    }
    for role in ("vision", "reference"):
        js = getattr(rec, role)
        if js is not None:
            p = np.where(js.available[..., None], js.position_m, np.nan)
            out[role] = {
                "T": len(js),
                "duration_s": round(float(js.t_s[-1] - js.t_s[0]), 4) if len(js) else 0.0,
                "joints": list(js.joints),
                "median_norm_m": _median_norm(p),
                "available": round(float(js.available.mean()), 6) if js.available.size else None,
            }
    return out


def _targets(root: Path) -> list[Path]:
    items = [root]
    for p in sorted(root.rglob("*")):
        if p.is_file() and (
            p.suffix.lower() in _SKIP_SUFFIXES or p.name.upper().startswith("LICENSE")
        ):
            continue
        items.append(p)
    return items


def run(root: Path) -> dict:
    from kinefuse.io import load

    result = {}
    targets = _targets(root)
    for k, p in enumerate(targets):
        key = str(p.relative_to(root)) + ("/" if p.is_dir() else "")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                rec = load(p)
                result[key] = {"status": "ok", **_summary(rec)}
            except Exception as e:  # the point is to record every failure
                result[key] = {"status": "error", "error": f"{type(e).__name__}: {e}"[:300]}
        if (k + 1) % 100 == 0:
            print(f"{k + 1}/{len(targets)}", file=sys.stderr)
    return result


def diff(a: dict, b: dict) -> int:
    """Print what changed between two summaries; return the number of entries that stopped loading."""
    lost = 0
    for key in sorted(set(a) | set(b)):
        ea, eb = a.get(key), b.get(key)
        if ea == eb:
            continue
        sa = ea["status"] if ea else "absent"
        sb = eb["status"] if eb else "absent"
        if sa == "ok" and sb != "ok":
            lost += 1
            print(f"STOPPED LOADING  {key}: {eb.get('error') if eb else 'absent'}")
        elif sa != "ok" and sb == "ok":
            print(
                f"now loads        {key}: {eb.get('format')} (was {ea.get('error') if ea else 'absent'})"
            )
        elif sa == sb == "ok":
            changed = sorted(k for k in set(ea) | set(eb) if ea.get(k) != eb.get(k))
            print(f"content changed  {key}: {', '.join(changed)}")
            for k in changed:
                print(f"    before {k}: {json.dumps(ea.get(k))[:200]}")
                print(f"    after  {k}: {json.dumps(eb.get(k))[:200]}")
        else:
            print(
                f"error changed    {key}:\n    before: {ea.get('error')}\n    after:  {eb.get('error')}"
            )
    n_a = sum(v["status"] == "ok" for v in a.values())
    n_b = sum(v["status"] == "ok" for v in b.values())
    print(f"loaded: {n_a}/{len(a)} before, {n_b}/{len(b)} after; stopped loading: {lost}")
    return lost


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("root", nargs="?", type=Path)
    ap.add_argument("--out", type=Path)
    ap.add_argument("--diff", nargs=2, type=Path, metavar=("BEFORE", "AFTER"))
    args = ap.parse_args(argv)
    if args.diff:
        a, b = (json.loads(p.read_text()) for p in args.diff)
        return 1 if diff(a, b) else 0
    if args.root is None or args.out is None:
        ap.error("give ROOT and --out, or --diff BEFORE AFTER")
    if args.out.exists():
        ap.error(f"{args.out} exists; refusing to overwrite it")
    res = run(args.root)
    args.out.write_text(json.dumps(res, indent=1, sort_keys=True))
    print(f"{sum(v['status'] == 'ok' for v in res.values())}/{len(res)} loaded -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
