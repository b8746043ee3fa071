#!/usr/bin/env python3
"""Compare edo's section areas with trimesh's `section_multiplane` on the shared meshes.

An independent check (ISSUE 3, "correctness against something no one here wrote"): for each
mesh, cut at the mid-heights of 0.2 mm uniform layers with both slicers and compare the
areas. Exit status 1 if any layer disagrees by more than the tolerance.

    python3 -m venv /tmp/venv && /tmp/venv/bin/pip install trimesh shapely numpy
    cargo build --release --example slice_areas
    /tmp/venv/bin/python tests/compare_trimesh.py [--edo target/release/examples/slice_areas]
        [--meshes ../shared/meshes] [--layer 0.2] [--tol 0.005]

Relative difference per layer: |edo - trimesh| / max(trimesh, 1 mm²), so that layers of
under 1 mm² (a tip, a sliver) are compared in absolute terms.
"""
import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np
import trimesh

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)

# Closed meshes only: the open bunny is refused by edo (see docs/mesh-and-slicing.md).
MESHES = ["femur.stl", "hip.stl", "3DBenchy.stl", "3DBenchy.3mf"]


def trimesh_areas(path, heights):
    mesh = trimesh.load(path, force="mesh")
    z0 = float(mesh.bounds[0][2])
    start = time.perf_counter()
    sections = mesh.section_multiplane(
        plane_origin=[0.0, 0.0, z0], plane_normal=[0.0, 0.0, 1.0], heights=[h - z0 for h in heights]
    )
    areas = [0.0 if s is None else float(s.area) for s in sections]
    return areas, time.perf_counter() - start


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--edo", default=os.path.join(ROOT, "target/release/examples/slice_areas"))
    ap.add_argument("--meshes", default=os.path.join(ROOT, "../shared/meshes"))
    ap.add_argument("--layer", type=float, default=0.2)
    ap.add_argument("--tol", type=float, default=0.005)
    args = ap.parse_args()
    if not os.path.isdir(args.meshes):
        print(f"note: {args.meshes} missing, nothing to compare")
        return 0
    worst_all = 0.0
    failed = False
    for name in MESHES:
        path = os.path.join(args.meshes, name)
        if not os.path.exists(path):
            print(f"note: {path} missing, skipped")
            continue
        out = subprocess.run([args.edo, path, "--uniform", str(args.layer)], check=True,
                             capture_output=True, text=True).stdout
        edo = json.loads(out)
        # Cut trimesh where edo really cut (0.1 µm off vertex heights, so that a flat facet
        # at a layer's mid-height falls on the same side in both).
        heights = [s["cut_z_mm"] for s in edo["sections"]]
        ea = np.array([s["area_mm2"] for s in edo["sections"]])
        ta, t_secs = trimesh_areas(path, heights)
        ta = np.array(ta)
        rel = np.abs(ea - ta) / np.maximum(ta, 1.0)
        worst = int(np.argmax(rel))
        worst_all = max(worst_all, float(rel[worst]))
        ok = rel[worst] <= args.tol
        failed |= not ok
        print(json.dumps({
            "mesh": name, "layers": len(heights),
            "max_rel_diff": float(rel[worst]), "mean_rel_diff": float(rel.mean()),
            "worst_z_mm": heights[worst], "edo_mm2": float(ea[worst]), "trimesh_mm2": float(ta[worst]),
            "total_area_rel_diff": float(abs(ea.sum() - ta.sum()) / ta.sum()),
            "edo_sections_s": edo["seconds"], "trimesh_sections_s": t_secs,
            "speedup": t_secs / max(edo["seconds"], 1e-9), "ok": bool(ok),
        }))
    print(f"worst layer disagreement {worst_all:.3%} (tolerance {args.tol:.1%})")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
