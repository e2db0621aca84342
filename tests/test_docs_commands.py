"""The guides' commands run as written from the checkout, in a fresh shell.

Every fenced ``bash`` block of README.md, docs/*.md and docs/guides/*.md is read command by command. Each
command must name what runs it: a script of ``scripts/`` (``bash scripts/X.sh``), a program of the project's
venv (``.venv/bin/NAME``: a bare ``python`` has no gymnasium, a bare ``swimmer_sim_node`` is not on a fresh
shell's path), or any venv program once the block activated the venv (``. .venv/bin/activate``); ``ros2`` only
where the page says it is for a Jazzy install. Every ``--option`` a command gives must be one its tool's
``--help`` lists (the tool run for real, once per tool), so a renamed or removed option in a guide fails here;
the options after a bring-up's ``--`` are morph-train's. Each block must also parse as bash (``bash -n``).
No DDS: nothing is started but ``--help``.
"""

from __future__ import annotations

import functools
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # every test here starts processes (nodes, bring-ups, installs)

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
GUIDES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), *sorted((ROOT / "docs" / "guides").glob("*.md"))]
BLOCK = re.compile(r"```(?:bash|sh)\n(.*?)```", re.S)
KEYWORDS = {"for", "do", "done", "then", "fi", "if", "else", "while", "time", "cd", "echo", "export", "mkdir"}
OPERATORS = {";", "&&", "||", "|", "&", "(", ")"}
SCRIPT_TRAINER = {"live.sh", "bag_rounds.sh"}  # options after -- go to morph-train
JAZZY = "Jazzy install"
NODES = {"swimmer_sim_node", "morph_policy_node"}
"""the nodes' programs: found in the venv, their parameters not checked here (the nodes' own tests do)"""


def blocks() -> list[tuple[str, str, str]]:
    """(page, the text before the block, the block) of every fenced bash block of the guides."""
    out = []
    for page in GUIDES:
        text = page.read_text()
        for m in BLOCK.finditer(text):
            out.append((str(page.relative_to(ROOT)), text[max(0, m.start() - 400) : m.start()], m.group(1)))
    return out


def commands(block: str) -> list[tuple[str, list[str]]]:
    """(line, words) of every simple command in ``block``: continuations joined, comments dropped, split at
    ``;``, ``&&``, ``|`` ...; leading assignments and shell keywords left out."""
    out = []
    for line in block.replace("\\\n", " ").splitlines():
        lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|()")
        lexer.whitespace_split, lexer.commenters = True, "#"
        try:
            words = list(lexer)
        except ValueError as err:  # unbalanced quotes: bash -n says more
            raise AssertionError(f"{line!r}: {err}") from None
        current: list[str] = []
        for word in [*words, ";"]:
            if word in OPERATORS:
                if current:
                    out.append((line, current))
                current = []
            else:
                current.append(word)
    cleaned = []
    for line, words in out:
        while words and (re.match(r"^[A-Za-z_]\w*=", words[0]) or words[0] in KEYWORDS):
            if words[0] in ("for",):  # for x in ...: the list is no command
                words = []
                break
            if words[0].startswith(("ANT=$(", "ANT=`")) or "=$(" in words[0]:  # the command in $( ) runs
                words = [words[0].split("$(", 1)[1], *words[1:]]
                break
            words = words[1:]
        if words:
            cleaned.append((line, words))
    return cleaned


@functools.cache
def help_text(*cmd: str) -> str:
    done = subprocess.run([*cmd, "--help"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, f"{' '.join(cmd)} --help: exit {done.returncode}: {done.stderr[-500:]}"
    return done.stdout


def options(words: list[str]) -> list[str]:
    """The --options of ``words`` (placeholders' brackets and =values left out), up to --ros-args."""
    out = []
    for word in words:
        if word == "--ros-args":
            break
        word = word.strip("[]")
        if word.startswith("--") and len(word) > 2:
            out.append(word.split("=", 1)[0])
    return out


def tool(words: list[str], venv_active: bool) -> tuple[tuple[str, ...] | None, list[str], str]:
    """(the command whose --help lists ``words``' options, or None for a file of bench/; the words after the
    tool; a complaint, '' when the command is runnable as written)."""
    first = words[0]
    if first == "bash":
        script = words[1] if len(words) > 1 else ""
        if not (script.startswith("scripts/") and (ROOT / script).is_file()):
            return None, [], f"bash {script}: not a script of scripts/"
        if script == "scripts/in_netns.sh":
            return ("in_netns",), words[2:], ""
        return ("bash", script), words[2:], ""
    if first.startswith(".venv/bin/"):
        name = first.removeprefix(".venv/bin/")
    elif venv_active and (BIN / first).exists():
        name = first
    else:
        return None, [], f"{first}: not runnable from a fresh shell (write .venv/bin/{first} or activate the venv)"
    if not (BIN / name).exists():
        return None, [], f"{first}: no such program in the venv"
    rest = words[1:]
    if name in ("python", "python3"):
        if rest[:1] == ["-m"] and len(rest) > 1:
            return (str(BIN / "python"), "-m", rest[1]), rest[2:], ""
        if rest and rest[0].endswith(".py"):
            return None, rest[1:], "" if (ROOT / rest[0]).is_file() else f"{rest[0]}: no such file"
        return None, rest, ""  # python -c '...'
    if name in NODES:  # ROS parameters (-p name:=value after --ros-args): no --help to ask, it would start
        return None, rest, ""
    if name in ("mkdocs", "ray", "ruff"):
        sub = rest[:1] if rest and not rest[0].startswith("-") else []
        return (str(BIN / name), *sub), rest[len(sub) :], ""
    sub = rest[:1] if name in ("morph-bag", "morph-keys") and rest else []
    return (str(BIN / name), *sub), rest[len(sub) :], ""


def check_command(words: list[str], venv_active: bool, before: str, line: str) -> list[str]:
    if words[0] == "ros2":
        return [] if JAZZY in before or JAZZY in line else [f"{line}: ros2 on a page that does not say '{JAZZY}'"]
    if words[0] in (".", "source"):
        return []
    cmd, rest, complaint = tool(words, venv_active)
    if complaint:
        return [f"{line}: {complaint}"]
    if cmd == ("in_netns",):  # the command it runs is checked as one of its own
        return check_command(rest, venv_active, before, line) if rest else []
    if cmd is None:
        return []
    own, trainer = rest, []
    if cmd[0] == "bash" and Path(cmd[1]).name in SCRIPT_TRAINER and "--" in rest:
        cut = rest.index("--")
        own, trainer = rest[:cut], rest[cut + 1 :]
    problems = []
    text = help_text(*cmd)
    problems += [f"{line}: {opt} is not an option of {' '.join(cmd)}" for opt in options(own) if opt not in text]
    if trainer:
        train = help_text(str(BIN / "morph-train"))
        problems += [f"{line}: {opt} (after --) is not an option of morph-train" for opt in options(trainer)
                     if opt not in train]  # fmt: skip
    return problems


ALL = blocks()


def test_the_guides_have_commands():
    pages = {page for page, _, _ in ALL}
    assert {"README.md", "docs/your_robot.md", "docs/guides/nodes.md", "docs/centipedes.md"} <= pages


@pytest.mark.parametrize("page", sorted({page for page, _, _ in ALL}))
def test_every_command_of_the_guides_runs_as_written_from_the_checkout(page):
    problems = []
    for _, before, block in (b for b in ALL if b[0] == page):
        syntax = subprocess.run(["bash", "-n"], input=block, capture_output=True, text=True, timeout=30)
        if syntax.returncode != 0:
            problems.append(f"not bash: {syntax.stderr.strip()}")
        venv_active = False
        for line, words in commands(block):
            if words[0] in (".", "source") and words[1:2] == [".venv/bin/activate"]:
                venv_active = True
            problems += check_command(words, venv_active, before, line)
    assert problems == [], "\n".join(problems)
