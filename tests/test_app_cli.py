"""What both apps share (graphopt/apps/_cli.py): one-line errors, option and output checks,
solver names, JSON output, the recording wrapper and the ``main`` wrapper."""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import pytest

from graphopt import StoppingConfig
from graphopt.apps import _cli, bal, direct_ba, g2o
from graphopt.apps._cli import (
    AppError,
    OneLineParser,
    RunRecording,
    add_solver_option,
    add_stopping_options,
    check_outputs,
    check_run_options,
    optimize_recorded,
    run_main,
    stopping_config,
    write_json,
)
from graphopt.solvers import SOLVERS


def test_one_line_parser_error(capsys: pytest.CaptureFixture[str]) -> None:
    p = OneLineParser(prog="tool")
    p.add_argument("--n", type=int)
    with pytest.raises(SystemExit) as info:
        p.parse_args(["--n", "x"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert err == "tool: error: argument --n: invalid int value: 'x' (see --help)\n"


@pytest.mark.parametrize("parser", [bal.build_parser, direct_ba.build_parser, g2o.build_parser])
def test_both_apps_take_the_library_solver_names(parser) -> None:
    p = parser()
    assert p.parse_args([]).solver == "auto"
    for name in SOLVERS:
        assert p.parse_args(["--solver", name]).solver == name
    assert {"auto", "cholmod", "dense", "pcg"} <= set(SOLVERS)
    with pytest.raises(SystemExit) as info:
        p.parse_args(["--solver", "magic"])
    assert info.value.code == 2
    own = OneLineParser(prog="x")
    add_solver_option(own)
    assert own.parse_args(["--solver", "pcg"]).solver == "pcg"
    assert "--solver {" + ",".join(SOLVERS) + "}" in own.format_help()


def _stopping_args(*argv: str):
    p = OneLineParser(prog="tool")
    add_stopping_options(p)
    return p.parse_args(list(argv))


@pytest.mark.parametrize(
    ("argv", "delta", "message"),
    [(["-i", "-1"], 1.0, "--iterations must be >= 0, got -1"),
     ([], 0.0, "--robust-delta must be positive, got 0"),
     ([], -2.5, "--robust-delta must be positive, got -2.5"),
     ([], float("nan"), "--robust-delta must be positive, got nan"),
     ([], float("inf"), "--robust-delta must be positive, got inf"),
     (["--function-tolerance=-1e-3"], 1.0,
      "--function-tolerance must be a finite number >= 0, got -0.001"),
     (["--gradient-tolerance", "nan"], 1.0,
      "--gradient-tolerance must be a finite number >= 0, got nan"),
     (["--gain", "inf"], 1.0, "--gain must be a finite number >= 0, got inf")],
)
def test_check_run_options_rejects(argv: list[str], delta: float, message: str) -> None:
    with pytest.raises(AppError) as info:
        check_run_options(_stopping_args(*argv), delta)
    assert str(info.value) == message


def test_check_run_options_accepts() -> None:
    assert check_run_options(_stopping_args("-i", "0"), 1e-9) is None
    assert check_run_options(_stopping_args("--iterations", "40"), 0.5) is None


def test_stopping_options_make_the_stopping_config() -> None:
    assert stopping_config(_stopping_args()) == StoppingConfig(max_iterations=100)
    got = stopping_config(_stopping_args("-i", "7", "--function-tolerance", "0",
                                         "--gradient-tolerance", "1e-3",
                                         "--parameter-tolerance", "2e-5", "--gain", "1e-4"))
    assert got == StoppingConfig(7, 0.0, 1e-3, 2e-5, 1e-4)


def test_check_outputs(tmp_path: Path) -> None:
    data = tmp_path / "in.txt"
    data.write_text("x")
    ok = {"--json": str(tmp_path / "a.json"), "--rrd": None, "--png": str(tmp_path / "b.png")}
    assert check_outputs(ok, inputs=[str(data), None]) is None
    cases = [
        ({"--json": str(tmp_path / "no" / "a.json")}, "does not exist"),
        ({"--png": str(tmp_path)}, f"--png {tmp_path}: is a directory"),
        ({"--json": str(data)}, "refusing to overwrite the input"),
        ({"--json": str(tmp_path / "s.x"), "--rrd": str(tmp_path / "." / "s.x")},
         "two outputs name the same file"),
    ]
    for outputs, fragment in cases:
        with pytest.raises(AppError) as info:
            check_outputs(outputs, inputs=[str(data)])
        assert fragment in str(info.value), (outputs, str(info.value))
        assert "\n" not in str(info.value)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.txt"]  # nothing created


def test_write_json_is_strict_and_atomic(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    path.write_text("old")
    write_json(path, {"a": 1.5, "nan": float("nan"), "nested": {"inf": float("-inf"), "k": 2},
                      "history": [1.0, float("nan"), 3], "name": "x"})

    def no_constants(name: str) -> None:
        raise AssertionError(f"non-standard JSON constant {name}")

    data = json.loads(path.read_text(), parse_constant=no_constants)
    assert data == {"a": 1.5, "nan": None, "nested": {"inf": None, "k": 2},
                    "history": [1.0, None, 3], "name": "x"}
    assert path.read_text().endswith("}\n")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.json"]


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="tool")
    p.add_argument("--what", default="ok")
    return p


@pytest.mark.parametrize(
    ("raised", "code", "stderr"),
    [
        (None, 0, ""),
        (AppError("bad input\nsecond line"), 1, "tool: error: bad input\n"),
        (FileNotFoundError(2, "No such file", "x.txt"), 1,
         "tool: error: [Errno 2] No such file: 'x.txt'\n"),
        (LookupError("user-facing"), 1, "tool: error: user-facing\n"),
        (RuntimeError("boom\ntrace"), 1, "tool: error: RuntimeError: boom\n"),
        (KeyboardInterrupt(), 130, "tool: interrupted; no output written\n"),
    ],
)
def test_run_main_reports_one_line(monkeypatch: pytest.MonkeyPatch,
                                   capsys: pytest.CaptureFixture[str],
                                   raised: BaseException | None, code: int, stderr: str) -> None:
    monkeypatch.delenv("GRAPHOPT_DEBUG", raising=False)
    seen: list[str] = []

    def run(args: argparse.Namespace) -> None:
        seen.append(args.what)
        if raised is not None:
            raise raised

    assert run_main("tool", _parser(), run, ["--what", "w"], user_errors=(LookupError,)) == code
    assert seen == ["w"]
    assert capsys.readouterr().err == stderr


def test_run_main_debug_shows_the_exception(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("GRAPHOPT_DEBUG", "1")

    def run(args: argparse.Namespace) -> None:
        raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        run_main("tool", _parser(), run, [])


class _Optimizer:
    def __init__(self, fail: bool) -> None:
        self.fail = fail

    def optimize(self, iterations: int) -> str:
        if self.fail:
            raise FloatingPointError("diverged")
        return f"done {iterations}"


def test_recording_is_timed_and_discarded_on_failure(tmp_path: Path) -> None:
    path = tmp_path / "run.rrd"
    rec = RunRecording(str(path), "tool", camera_xyz="RDF")
    with rec.timed() as recorder:
        recorder.set_iteration(0)
        time.sleep(0.02)
    assert 0.02 <= rec.seconds < 5.0
    with pytest.raises(FloatingPointError):
        optimize_recorded(_Optimizer(fail=True), 3, rec)
    assert os.listdir(tmp_path) == []  # no recording, no temporary file

    rec = RunRecording(str(path), "tool", camera_xyz="RUB")
    assert optimize_recorded(_Optimizer(fail=False), 3, rec) == "done 3"
    rec.close()
    assert path.stat().st_size > 0 and os.listdir(tmp_path) == ["run.rrd"]
    assert optimize_recorded(_Optimizer(fail=False), 2, None) == "done 2"


def test_every_app_writes_the_common_json_keys(tmp_path: Path, monkeypatch) -> None:
    """One schema: the same keys, with the same meaning, in all three apps' JSON."""
    from graphopt.apps import bal, direct_ba, g2o

    monkeypatch.setattr(direct_ba, "SYNTHETIC", {
        "n_frames": 3, "n_points": 200, "size": (320, 240), "seed": 2,
        "intrinsics": (140.0, 145.0, 160.0, 120.0)})
    runs = {
        "bal": (bal.main, ["--iterations", "2", "--robust", "huber"]),
        "direct_ba": (direct_ba.main, ["--iterations", "2"]),
        "g2o": (g2o.main, ["--iterations", "2", "--poses", "60", "--solver", "dense"]),
    }
    for name, (main, argv) in runs.items():
        js = tmp_path / f"{name}.json"
        assert main([*argv, "--quiet", "--json", str(js)]) == 0, name
        s = json.loads(js.read_text())
        assert set(_cli.COMMON_KEYS) <= set(s), (name, set(_cli.COMMON_KEYS) - set(s))
        assert s["solver"] in ("dense", "cholmod", "scipy", "pcg"), (name, s["solver"])
        assert s["algorithm"] == "lm" and s["iterations"] == 2 and s["stop_reason"] == "iterations"
        assert s["final_chi2"] < s["initial_chi2"], name
    assert json.loads((tmp_path / "bal.json").read_text())["robust_kernel"] == "huber:1"
    assert json.loads((tmp_path / "direct_ba.json").read_text())["robust_kernel"] == "huber:0.5"
    assert json.loads((tmp_path / "g2o.json").read_text())["solver_requested"] == "dense"


def _interrupt_run(tmp_path: Path, signals: list[int]) -> tuple[int, str]:
    """Run graphopt-g2o on a large generated graph; send ``signals`` once it is iterating."""
    import signal as _signal
    import subprocess
    import sys

    js = tmp_path / "run.json"
    proc = subprocess.Popen(
        [sys.executable, "-P", "-m", "graphopt.apps.g2o", "--poses", "5000", "-i", "500",
         "--lm-schedule", "g2o", "--json", str(js)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=tmp_path)
    assert proc.stderr is not None
    lines = []
    for line in proc.stderr:  # g2o's iteration lines: the optimisation is under way
        lines.append(line)
        if line.startswith("iteration= 1\t"):
            break
    for sig in signals:
        proc.send_signal(sig)
        time.sleep(0.05)
    _, err = proc.communicate(timeout=60)
    assert sig in (_signal.SIGINT, _signal.SIGTERM)
    return proc.returncode, "".join(lines) + err


@pytest.mark.parametrize(("sig", "code", "word"),
                         [(2, 130, "interrupted"), (15, 143, "terminated")])
def test_a_signal_ends_the_run_with_its_outputs(tmp_path: Path, sig: int, code: int,
                                                word: str) -> None:
    rc, err = _interrupt_run(tmp_path, [sig])
    assert rc == code, err
    assert f"{word}: the outputs were written from the best estimate" in err
    s = json.loads((tmp_path / "run.json").read_text())
    assert s["stop_reason"] == "interrupted" and 2 <= s["iterations"] < 500
    assert s["final_chi2"] < s["initial_chi2"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.json"]  # no temporary file


def test_a_second_signal_aborts_at_once() -> None:
    """The first signal asks the optimizer to stop at its next safe point; the second raises.

    (Python runs signal handlers between bytecodes, so two signals that arrive during one long
    C call — a factorisation — count as one: the run then ends with its outputs.)
    """
    import signal as _signal

    class Opt:
        stops = 0

        def stop(self) -> None:
            Opt.stops += 1

    before = _signal.getsignal(_signal.SIGINT)
    with pytest.raises(KeyboardInterrupt), _cli._interruptible(Opt()):
        os.kill(os.getpid(), _signal.SIGINT)
        time.sleep(0.01)
        assert Opt.stops == 1 and _cli._interrupted == _signal.SIGINT
        os.kill(os.getpid(), _signal.SIGINT)
        time.sleep(0.5)
    assert _signal.getsignal(_signal.SIGINT) is before  # the handlers are restored
    with pytest.raises(_cli.Terminated), _cli._interruptible(Opt()):
        os.kill(os.getpid(), _signal.SIGTERM)
        time.sleep(0.01)
        os.kill(os.getpid(), _signal.SIGTERM)
        time.sleep(0.5)
    assert Opt.stops == 2
