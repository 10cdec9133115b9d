#!/usr/bin/env python3
"""Bakes obscurances with a progress bar; Ctrl-C cancels the bake on the server.

    bake_obscurances.py --server 127.0.0.1:50051 --scene cornell_box_visq --d-max 0.5 --out w.npy

Writes W per atlas texel as a (height, width, 3) float32 .npy.
"""
import argparse
import sys

import numpy as np

import visq


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", default="127.0.0.1:50051")
    parser.add_argument("--scene", required=True)
    parser.add_argument("--d-max", type=float, required=True, help="occlusion distance in scene units")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--directions", type=int, default=64)
    parser.add_argument("--out", required=True)
    args = parser.parse_args()

    def progress(p):
        print(f"\r{p.directions_done}/{p.directions_total} directions, ~{p.estimated_s_left:.1f} s left ",
              end="", file=sys.stderr, flush=True)

    try:
        with visq.Client(args.server) as client:
            bake = client.compute_obscurances(args.scene, args.d_max, resolution=args.resolution,
                                              directions=args.directions, progress=progress)
    except KeyboardInterrupt:
        print("\ncancelled", file=sys.stderr)
        return 130
    except (visq.VisqError, ValueError) as error:
        print(f"\nbake_obscurances: {error}", file=sys.stderr)
        return 1
    print(file=sys.stderr)
    np.save(args.out, bake.w)
    print(f"{args.out}: W {bake.w.shape}, mean over estimated texels {bake.w[bake.estimated].mean():.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
