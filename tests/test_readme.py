"""Every fenced code block of README.md is run or checked.

- ```bash blocks: each command runs in a fresh temporary folder holding a copy of
  ``examples/`` (the README's paths are relative to the repository root) and must exit with
  the status its trailing ``# exit N`` comment states (0 without one). ``pip install`` is not
  re-run (CI has just installed the package); the quick start's two commands must equal, in
  effect, what ``.ci/run`` runs, and the whole test suite's command is checked by its text
  only (it would run this file again).
- ```text blocks: output the bash block before them prints (numbers within 2 %).
- ```python blocks: run in a fresh interpreter (float64, as each block sets it) in such a
  folder, exit 0.
- ```toml blocks: parsed with tomllib; a complete scene (``[sample]`` and ``[[profiles]]``)
  is loaded with ``fwdfit.load_scene``; a fragment is loaded merged into the complete one,
  its tables named there written from the README's ```csv block.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

import fwdfit

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
KNOWN = {"bash", "python", "toml", "csv", "text"}
QUICK_START = ("python3 -m pip install . && fwdfit fit examples/al_block/scene.toml --out out/al_block",
               'python3 -m pip install ".[test]" && python3 -m pytest -q -n 2 --dist loadfile tests')
# Flags of .ci/run that only quieten its output; the README's commands leave them out.
QUIET_FLAGS = ("--quiet", "-p no:cacheprovider")
TIMEOUT_S = 300


def _blocks() -> list[tuple[str, str, int]]:
    """(language, text, line number of the opening fence) of every fenced block."""
    blocks, lines, i = [], README.read_text(encoding="utf-8").splitlines(), 0
    while i < len(lines):
        opening = re.match(r"^```(\S*)\s*$", lines[i])
        if opening:
            start, i = i, i + 1
            while not lines[i].startswith("```"):
                i += 1
            blocks.append((opening.group(1), "\n".join(lines[start + 1:i]) + "\n", start + 1))
        i += 1
    return blocks


BLOCKS = _blocks()


def _of(language: str) -> list[tuple[str, str, int]]:
    return [block for block in BLOCKS if block[0] == language]


def _commands(text: str) -> list[tuple[str, int]]:
    """The block's commands (continuation lines joined) and the exit status each states."""
    commands, pending = [], ""
    for line in text.splitlines():
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        line, pending = pending + line, ""
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        status = re.search(r"\s#\s*exit (\d+)\s*$", line)
        commands.append((line[:status.start()].strip() if status else line.strip(),
                         int(status.group(1)) if status else 0))
    return commands


def _workspace(tmp_path: Path) -> Path:
    """A fresh folder holding what the README's commands read (examples/)."""
    work = tmp_path / "work"
    shutil.copytree(ROOT / "examples", work / "examples",
                    ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    return work


def _env() -> dict:
    env = dict(os.environ)
    # The interpreter running the tests, and its fwdfit script, come first on PATH.
    env["PATH"] = os.pathsep.join([str(Path(sys.executable).parent), env.get("PATH", "")])
    env.pop("PYTHONPATH", None)
    return env


def _ci_commands() -> list[str]:
    """The commands .ci/run runs (not its shell set-up)."""
    commands = []
    for line in (ROOT / ".ci" / "run").read_text().splitlines():
        line = line.strip()
        if not line or line.startswith("#") or line.startswith(("set ", "cd ")):
            continue
        for flag in QUIET_FLAGS:
            line = line.replace(f" {flag}", "")
        commands.append(line)
    return commands


def _split(command: str) -> list[str]:
    return [part.strip() for part in command.split("&&")]


def test_every_block_is_one_the_test_knows():
    assert BLOCKS, "README.md has no code blocks"
    unknown = [(language, line) for language, _, line in BLOCKS if language not in KNOWN]
    assert not unknown, f"blocks of a language this test does not run (language, line): {unknown}"


def test_readme_is_short():
    assert len(README.read_text(encoding="utf-8").splitlines()) < 400


def test_quick_start_commands_are_what_ci_runs():
    """The first two bash blocks are the quick start: each is one command, the first
    installs and fits the shipped example, the second installs the test extras and runs
    the whole suite, as .ci/run does (the same pip and pytest commands, less the flags that
    only quieten .ci/run's output)."""
    bash = _of("bash")
    assert [_commands(text) for _, text, _ in bash[:2]] == [[(QUICK_START[0], 0)], [(QUICK_START[1], 0)]]
    assert _ci_commands() == _split(QUICK_START[1])


def _run_block(text: str, work: Path) -> str:
    """Run the block's commands in ``work``; return what they printed (stdout + stderr)."""
    printed = []
    for command, status in _commands(text):
        parts = _split(command)
        if parts[0].startswith("python3 -m pip install"):
            parts = parts[1:]  # CI has just installed the package and its test extras
        if parts and parts[0] == _split(QUICK_START[1])[1]:
            continue  # the whole suite: checked by its text (test_quick_start_commands_are_what_ci_runs)
        if not parts:
            continue
        done = subprocess.run(["bash", "-c", " && ".join(parts)], cwd=work, env=_env(),
                              capture_output=True, text=True, timeout=TIMEOUT_S)
        assert done.returncode == status, (
            f"{command!r}: exit {done.returncode}, the README says {status}\n"
            f"stdout:\n{done.stdout[-3000:]}\nstderr:\n{done.stderr[-3000:]}")
        errors = [line for line in done.stderr.splitlines() if line.startswith("fwdfit: ")]
        if status == 1:
            assert len(errors) == 1 and errors[0].startswith("fwdfit: error: "), done.stderr
        if status == 3:
            assert [line for line in errors if line.startswith("fwdfit: poor fit: ")], done.stderr
        assert "Traceback" not in done.stderr, done.stderr
        printed.append(done.stdout + done.stderr)
    return "".join(printed)


def _follows(bash_line: int) -> list[str]:
    """The text blocks between this bash block and the next code block of another kind."""
    texts, after = [], False
    for language, text, line in BLOCKS:
        if line == bash_line:
            after = True
        elif after and language == "text":
            texts.append(text)
        elif after:
            break
    return texts


_NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?")


def _same_line(expected: str, printed: str) -> bool:
    """Whether ``printed`` holds ``expected`` with its numbers within 2 % (or 0.05)."""
    skeleton = _NUMBER.sub("#", expected)
    for line in printed.splitlines():
        if _NUMBER.sub("#", line) == skeleton:
            want, got = (np.array([float(x) for x in _NUMBER.findall(s)]) for s in (expected, line))
            if np.all(np.abs(got - want) <= np.maximum(0.02 * np.abs(want), 0.05)):
                return True
    return False


@pytest.mark.parametrize("line", [line for _, _, line in _of("bash")], ids=lambda line: f"line{line}")
def test_bash_block(line, tmp_path):
    """Each command exits with the status the README states; the output the README shows
    after the block is what it printed."""
    text = next(text for language, text, at in BLOCKS if at == line)
    work = _workspace(tmp_path)
    printed = _run_block(text, work)
    if "fwdfit fit examples/al_block/scene.toml --out out/al_block" in text:
        assert (work / "out" / "al_block" / "result.json").is_file()
        assert (work / "out" / "al_block" / "fitted_scene.toml").is_file()
    for shown in _follows(line):
        for expected in shown.splitlines():
            assert _same_line(expected, printed), f"the README shows\n{expected}\nthe block printed\n{printed}"


@pytest.mark.parametrize("line", [line for _, _, line in _of("python")], ids=lambda line: f"line{line}")
def test_python_block(line, tmp_path):
    text = next(text for language, text, at in BLOCKS if at == line)
    assert 'jax.config.update("jax_enable_x64", True)' in text, "a Python block says its precision"
    work = _workspace(tmp_path)
    script = tmp_path / "block.py"
    script.write_text(text, encoding="utf-8")
    done = subprocess.run([sys.executable, str(script)], cwd=work, env=_env(),
                          capture_output=True, text=True, timeout=TIMEOUT_S)
    assert done.returncode == 0, f"stdout:\n{done.stdout[-3000:]}\nstderr:\n{done.stderr[-3000:]}"


def _complete_scene() -> dict:
    complete = [tomllib.loads(text) for _, text, _ in _of("toml")
                if {"sample", "profiles"} <= set(tomllib.loads(text))]
    assert complete, "the README shows no complete scene"
    return complete[0]


def _write_toml(table: dict, path: Path) -> None:
    """A scene dict as TOML (fwdfit writes scenes, not dicts: a small writer for this test)."""
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, str):
            return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        if isinstance(v, dict):
            return "{ " + ", ".join(f"{value(k)} = {value(x)}" for k, x in v.items()) + " }"
        return repr(v)

    out = []

    def table_lines(prefix, t, array=False):
        out.append(f"[[{prefix}]]" if array else f"[{prefix}]")
        subtables = []
        for k, v in t.items():
            if isinstance(v, dict) and k != "bounds":
                subtables.append((f"{prefix}.{k}", v, False))
            elif isinstance(v, list) and v and isinstance(v[0], dict):
                subtables += [(f"{prefix}.{k}", x, True) for x in v]
            else:
                out.append(f"{k} = {value(v)}")
        for name, sub, is_array in subtables:
            table_lines(name, sub, is_array)

    for key, v in table.items():
        if key == "spectra":
            for name, spectrum in v.items():
                table_lines(f"spectra.{name}", spectrum)
        elif isinstance(v, list):
            for item in v:
                table_lines(key, item, True)
        else:
            table_lines(key, v)
    path.write_text("\n".join(out) + "\n", encoding="utf-8")


@pytest.mark.parametrize("line", [line for _, _, line in _of("toml")], ids=lambda line: f"line{line}")
def test_toml_block(line, tmp_path):
    text = next(text for language, text, at in BLOCKS if at == line)
    table = tomllib.loads(text)
    scene_path = tmp_path / "scene.toml"
    if {"sample", "profiles"} <= set(table):
        scene_path.write_text(text, encoding="utf-8")
        scene = fwdfit.load_scene(scene_path)
        assert [p.name for p in scene.profiles] == [p["name"] for p in table["profiles"]]
        return
    merged = {**_complete_scene(), **table}
    (csv_block,) = [text for _, text, _ in _of("csv")]
    for profile in merged.get("profiles", []):
        if "file" in profile:
            (tmp_path / profile["file"]).write_text(csv_block, encoding="utf-8")
    _write_toml(merged, scene_path)
    scene = fwdfit.load_scene(scene_path)
    for profile, given in zip(scene.profiles, merged.get("profiles", [])):
        if "file" in given:
            rows = np.loadtxt(csv_block.splitlines()[1:], delimiter=",")
            np.testing.assert_allclose(profile.T, rows[:, 1])
            if given.get("errors") == "estimate":
                assert profile.T_err is None  # the T_err column is ignored on purpose


def test_csv_block_is_a_profile_table():
    """The table's header is the documented columns; its x increase."""
    (text,) = [text for _, text, _ in _of("csv")]
    lines = text.splitlines()
    assert lines[0].split(",")[:2] == ["x_um", "T"]
    rows = np.loadtxt(lines[1:], delimiter=",")
    assert np.all(np.diff(rows[:, 0]) > 0)
