#!/usr/bin/env python3
"""Writes a hidden-sample map's visible fractions as a (height, width) float32 .npy.

    hidden_map.py --server 127.0.0.1:50051 --scene cornell_box_visq --out map.npy

The source and receiver default to the Cornell box's ceiling light and floor;
visible[y, x] is the fraction of the light's samples seen from floor texel
(x, y), y along the receiver's edge_v.
"""
import argparse
import sys

import grpc
import numpy as np

import visq


def patch(text, flag):
    try:
        origin, edge_u, edge_v = ([float(v) for v in part.split(",")] for part in text.split(";"))
        return visq.Patch(origin, edge_u, edge_v)
    except ValueError:
        raise SystemExit(f"{flag}: expected 'ox,oy,oz;ux,uy,uz;vx,vy,vz', got '{text}'")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--server", default="127.0.0.1:50051", help="HOST[:PORT] of visq-server")
    parser.add_argument("--scene", required=True)
    parser.add_argument("--out", required=True, help="the .npy file to write")
    parser.add_argument("--source", default="-0.25,1.99,-0.25;0.5,0,0;0,0,0.5")
    parser.add_argument("--receiver", default="-0.999,0.001,-0.999;1.998,0,0;0,0,1.998")
    parser.add_argument("--width", type=int, default=128)
    parser.add_argument("--height", type=int, default=128)
    parser.add_argument("--samples", type=int, default=256)
    parser.add_argument("--method", default="raster", help="raster, raycast or exact")
    parser.add_argument("--token-file", help="file holding the bearer token")
    args = parser.parse_args()
    try:
        with visq.Client(args.server, token_file=args.token_file) as client:
            result = client.hidden_sample_map(args.scene, patch(args.source, "--source"),
                                              patch(args.receiver, "--receiver"), width=args.width,
                                              height=args.height, samples=args.samples, method=args.method)
    except (visq.VisqError, ValueError) as error:
        print(f"hidden_map: {error}", file=sys.stderr)
        return 2 if getattr(error, "code", grpc.StatusCode.INVALID_ARGUMENT) == grpc.StatusCode.INVALID_ARGUMENT else 1
    np.save(args.out, result.visible_fraction)
    accuracy = result.accuracy
    print(f"{args.out}: {result.visible_fraction.shape} visible fractions, mean "
          f"{result.visible_fraction.mean():.4f}, {accuracy.method} +-{accuracy.error_bound:.4f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
