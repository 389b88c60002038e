#!/usr/bin/env python3
"""Compare two per-pixel hit-distance dumps (`slimkd render --dump-t`, or any
ray tracer writing W*H little-endian f32, row-major, top row first, +inf for
a miss).

    tools/compare-t.py A.f32 B.f32 [--rel 1e-4]

Prints the pixel count, hits in each, hit/miss disagreements, the number of
pixels whose distances differ by more than the relative tolerance, the
largest relative difference, and both checksums (sum of f64(t) over finite
t, row-major). Exits 1 when the files disagree beyond the tolerance.
Needs only the Python standard library.
"""
import argparse
import array
import math
import sys


def load(path):
    a = array.array("f")
    with open(path, "rb") as f:
        data = f.read()
    if len(data) % 4:
        sys.exit(f"{path}: size {len(data)} is not a multiple of 4")
    a.frombytes(data)
    if sys.byteorder != "little":
        a.byteswap()
    return a


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--rel", type=float, default=1e-4, help="relative tolerance on t")
    args = ap.parse_args()
    a, b = load(args.a), load(args.b)
    if len(a) != len(b):
        sys.exit(f"different pixel counts: {len(a)} vs {len(b)}")
    hit_a = hit_b = disagree = far = 0
    worst = 0.0
    sum_a = sum_b = 0.0
    for x, y in zip(a, b):
        fa, fb = math.isfinite(x), math.isfinite(y)
        hit_a += fa
        hit_b += fb
        if fa:
            sum_a += x
        if fb:
            sum_b += y
        if fa != fb:
            disagree += 1
        elif fa:
            rel = abs(x - y) / max(abs(x), abs(y), 1e-30)
            worst = max(worst, rel)
            far += rel > args.rel
    print(f"pixels {len(a)}  hits {hit_a} / {hit_b}  hit-miss disagreements {disagree}")
    print(f"beyond rel {args.rel}: {far}  largest relative difference {worst:.3g}")
    print(f"checksums {sum_a:.6f} / {sum_b:.6f}")
    sys.exit(1 if disagree or far else 0)


if __name__ == "__main__":
    main()
