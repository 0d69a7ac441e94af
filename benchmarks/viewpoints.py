"""How each data set sees its objects: the camera's elevation above every object's own z axis, its distance, and the
roll of that axis in the image, per instance, side by side for several BOP folders (rendered sets, real frames).

The refiner sees a crop: what it must have seen in training is the object from the camera's side. For the YCB scans,
whose z axis points up when the object stands as scanned, the elevation above the object's z axis says whether the
camera looks down on an upright object (+90 deg: from above, 0: from its side) or at one lying on its side or back;
the real frames hold objects in all of these. Instances with ``visib_fract >= --min-visib`` only. No image is read.

Usage (from the repository root)::

    python -m benchmarks.viewpoints --data robot=data/ycb9_robot --data real=REAL \\
        [--png benchmarks/viewpoints.png] [--json benchmarks/results/viewpoints/viewpoints.json]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from models.evaluate.record import write_json


def viewpoints(R: np.ndarray, t: np.ndarray) -> dict[str, np.ndarray]:
    """Per instance: ``elevation_deg`` of the camera above the object's z axis (asin of the z component, in the
    object frame, of the unit vector from the object's origin to the camera), ``distance_m`` (``|t|``) and
    ``roll_deg``, the angle in the image of the object's projected z axis from the image's up direction (``-y``),
    positive clockwise.

    Args:
        R: ``(N, 3, 3)`` object-to-camera rotations.
        t: ``(N, 3)`` object origins in the camera frame, metres.
    """
    R, t = np.asarray(R, float).reshape(-1, 3, 3), np.asarray(t, float).reshape(-1, 3)
    dist = np.linalg.norm(t, axis=1)
    to_cam = -np.einsum("nji,nj->ni", R, t) / np.maximum(dist, 1e-12)[:, None]  # R^T (-t) / |t|
    elevation = np.degrees(np.arcsin(np.clip(to_cam[:, 2], -1.0, 1.0)))
    z_cam = R[:, :, 2]  # the object's z axis in the camera frame
    roll = np.degrees(np.arctan2(z_cam[:, 0], -z_cam[:, 1]))
    return {"elevation_deg": elevation, "distance_m": dist, "roll_deg": roll}


def load_set(folder: Path, min_visib: float) -> dict:
    """Per-instance viewpoints and object names of one BOP folder."""
    from models.data import load_bop

    samples = load_bop(folder, min_visib=min_visib)
    if not samples:
        raise SystemExit(f"{folder}: no instance with visib_fract >= {min_visib}")
    v = viewpoints(np.stack([s.R for s in samples]), np.stack([s.t for s in samples]))
    v["objects"] = np.array([s.obj_id for s in samples])
    return v


def summary(v: dict) -> dict:
    """Percentiles (10, 50, 90) of each quantity, the instance count, and the share seen from below the object's
    equator (elevation < -10 deg: an object on its side or back seen from its underside's half)."""
    out = {"instances": int(len(v["distance_m"]))}
    for key in ("elevation_deg", "distance_m", "roll_deg"):
        out[key] = {f"p{p}": round(float(np.percentile(v[key], p)), 3) for p in (10, 50, 90)}
    out["share_elevation_below_-10"] = round(float(np.mean(v["elevation_deg"] < -10.0)), 4)
    return out


def plot(sets: dict[str, dict], png: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    spec = (("elevation_deg", np.linspace(-90, 90, 37), "camera elevation above the object's z axis (deg)"),
            ("distance_m", np.linspace(0, 2.5, 26), "distance to the object (m)"),
            ("roll_deg", np.linspace(-180, 180, 37), "roll of the object's z axis in the image (deg)"))
    for ax, (key, bins, label) in zip(axes, spec):
        for name, v in sets.items():
            ax.hist(v[key], bins=bins, density=True, histtype="step", linewidth=1.6, label=f"{name} (n={len(v[key])})")
        ax.set_xlabel(label)
    axes[0].set_ylabel("share of instances (density)")
    axes[0].legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", action="append", required=True, metavar="NAME=DIR",
                    help="a BOP folder of scenes, named (repeat)")
    ap.add_argument("--min-visib", type=float, default=0.3)
    ap.add_argument("--png", type=Path, help="histograms of the three quantities, one line per set")
    ap.add_argument("--json", type=Path, help="percentiles per set (and per object)")
    args = ap.parse_args(argv)
    sets = {}
    for item in args.data:
        name, sep, folder = item.partition("=")
        if not sep or not folder:
            ap.error(f"--data expects NAME=DIR; got {item!r}")
        sets[name] = load_set(Path(folder), args.min_visib)
    result = {"min_visib": args.min_visib, "sets": {}}
    for name, v in sets.items():
        per_object = {}
        for obj in sorted(set(v["objects"])):
            keep = v["objects"] == obj
            per_object[str(obj)] = summary({k: v[k][keep] for k in ("elevation_deg", "distance_m", "roll_deg")})
        result["sets"][name] = {**summary(v), "objects": per_object}
        s = result["sets"][name]
        print(f"{name:>12}: {s['instances']:6d} instances; elevation p10/50/90 {s['elevation_deg']['p10']:.0f}/"
              f"{s['elevation_deg']['p50']:.0f}/{s['elevation_deg']['p90']:.0f} deg, below -10: "
              f"{100 * s['share_elevation_below_-10']:.0f}%; distance p50 {s['distance_m']['p50']:.2f} m")
    if args.png:
        plot(sets, args.png)
        print(f"Wrote {args.png}")
    if args.json:
        write_json(args.json, result)
        print(f"Wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
