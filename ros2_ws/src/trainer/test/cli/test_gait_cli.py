"""``morph-gait``: the open-loop wave's speed per body, chains and named trees."""

import pytest

from morph_core.env.bodies import parse_bodies
from morph_core.env.gait import TravellingWave, run_gait
from trainer.cli.gait import main


def test_morph_gait_prints_each_bodys_speed(capsys):
    main(["--joints", "3", "--bodies", "y:1x1,star:3x1", "--seconds", "4"])
    rows = {line.split()[0]: float(line.split()[1]) for line in capsys.readouterr().out.splitlines()[2:]}
    y, star = parse_bodies("y:1x1,star:3x1").members()
    assert rows == pytest.approx(
        {
            name: run_gait(body, TravellingWave(), 4.0)
            for name, body in (("chain-3", 3), ("y-1x1", y), ("star-3x1", star))
        },
        abs=5e-5,
    )
    assert rows["y-1x1"] != rows["chain-3"]  # a Y of 3 joints is not the chain of 3


def test_morph_gait_refuses_a_random_family_and_a_bad_spec(capsys):
    for spec in ("random:3-5", "banana"):
        with pytest.raises(SystemExit):
            main(["--bodies", spec, "--seconds", "1"])
    assert "random family" in capsys.readouterr().err


def test_the_lengths_option_of_before_still_works_and_says_it_is_deprecated(capsys):
    main(["--lengths", "2", "--seconds", "1"])  # chain lengths are --joints in every tool
    out, err = capsys.readouterr()
    assert err == "morph-gait: warning: --lengths is deprecated: write --joints\n"
    assert [line.split()[0] for line in out.splitlines()[2:]] == ["chain-2"]
