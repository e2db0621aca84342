"""The Gymnasium ids register when an env is used, never on ``import morph_core`` (a robot's policy node has no
gymnasium): ``morph_core.env.registration`` and the env modules register them, and ``gymnasium.make`` then
builds the envs by id alone."""

import subprocess
import sys

import pytest


def _run(code: str) -> str:
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_import_morph_core_loads_and_registers_no_gymnasium():
    code = (
        "import sys\nimport morph_core\n"
        "print('gymnasium' in sys.modules, morph_core.ENV_ID, morph_core.CENTIPEDE_ENV_ID)\n"
        "import gymnasium\n"  # now loaded by hand: morph_core registered nothing in it
        "print(sorted(i for i in gymnasium.registry if i.startswith('Morph')))\n"
    )
    assert _run(code).splitlines() == ["False MorphSwimmer-v0 MorphCentipede-v0", "[]"]


@pytest.mark.parametrize(
    "module", ["morph_core.env.registration", "morph_core.env.swimmer_env", "morph_core.env.centipede"]
)
def test_importing_an_env_module_registers_both_ids_and_make_builds_them(module):
    code = (
        f"import gymnasium\nimport {module}\n"
        "swimmer = gymnasium.make('MorphSwimmer-v0', num_joints=3)\n"
        "centipede = gymnasium.make('MorphCentipede-v0', leg_pairs=2)\n"
        "s, _ = swimmer.reset(seed=0)\nc, _ = centipede.reset(seed=0)\n"
        "print(type(swimmer.unwrapped).__name__, len(s['joint_pos']), type(centipede.unwrapped).__name__, "
        "len(c['joint_pos']), swimmer.spec.max_episode_steps, centipede.spec.max_episode_steps)\n"
    )
    assert _run(code) == "MorphSwimmerEnv 3 MorphCentipedeEnv 8 1000 1000"


def test_registering_twice_is_harmless():
    import importlib

    import gymnasium

    import morph_core.env.registration as registration

    spec = gymnasium.spec("MorphSwimmer-v0")
    importlib.reload(registration)  # a second run of the module registers nothing anew
    assert gymnasium.spec("MorphSwimmer-v0") is spec
