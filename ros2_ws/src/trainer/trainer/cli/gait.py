"""``morph-gait``: swim chains of several lengths, and named trees, open-loop and print their forward speeds."""

from __future__ import annotations

from morph_core.env.bodies import body_label, parse_bodies
from morph_core.env.gait import TravellingWave, run_gait
from morph_core.util.config_cli import CommandLineParser


def main(argv: list[str] | None = None) -> None:
    parser = CommandLineParser(prog="morph-gait", description=__doc__)
    parser.add_argument("--joints", dest="lengths", type=int, nargs="*", default=[2, 3, 5, 6, 10, 15, 20], metavar="N",
                        help="chain lengths (joints) to swim, as morph-eval's --joints")  # fmt: skip
    parser.add_deprecated_alias("--lengths", "--joints")
    parser.add_argument("--bodies", default="", help="named trees too, an env.bodies spec (e.g. y:2x2,star:3x2)")
    parser.add_argument("--seconds", type=float, default=40.0, help="sim time per body")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    bodies: list = list(args.lengths)
    if args.bodies:
        try:
            members = parse_bodies(args.bodies).members()
        except ValueError as e:
            parser.error(str(e))
        if members is None:
            parser.error(f"--bodies {args.bodies!r} holds a random family: name the trees")
        bodies += members
    gait = TravellingWave()
    print(f"travelling wave {gait}, {args.seconds:.0f} s sim time per body (trees: the wave runs by depth)")
    print(f"{'body':>10}  {'speed [m/s]':>11}")
    for body in bodies:
        print(f"{body_label(body):>10}  {run_gait(body, gait, args.seconds, args.seed):>11.4f}")


if __name__ == "__main__":
    main()
