"""``morph-gait``: swim chains of several lengths open-loop and print their forward speeds."""

from __future__ import annotations

import argparse

from morph_core.env.gait import TravellingWave, run_gait


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--joints", type=int, nargs="+", default=[2, 3, 5, 6, 10, 15, 20])
    parser.add_argument("--seconds", type=float, default=40.0, help="sim time per chain")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    gait = TravellingWave()
    print(f"travelling wave {gait}, {args.seconds:.0f} s sim time per chain")
    print(f"{'joints':>6}  {'speed [m/s]':>11}")
    for n in args.joints:
        print(f"{n:>6}  {run_gait(n, gait, args.seconds, args.seed):>11.4f}")


if __name__ == "__main__":
    main()
