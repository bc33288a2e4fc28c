"""What the command-line apps share: one-line errors, option checks, solver names, JSON and rerun
outputs, and the ``main`` wrapper.

Every app reports a user's mistake (bad option, unreadable input, unwritable output) as one line
``PROG: error: …`` on stderr with exit status 1 (2 for a bad option, from the parser), and
replaces an existing output file only by a complete new one.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any, NoReturn

from graphopt.io.atomic import atomic_path, atomic_write
from graphopt.solvers import CHOLMOD_AVAILABLE, SOLVERS
from graphopt.stopping import StoppingConfig

__all__ = [
    "AppError",
    "OneLineParser",
    "RunRecording",
    "add_solver_option",
    "check_outputs",
    "check_run_options",
    "optimize_recorded",
    "run_main",
    "write_json",
    "write_png_image",
]


class AppError(Exception):
    """An error reported to the user as one line (no traceback), exit status 1."""


class OneLineParser(argparse.ArgumentParser):
    """argparse with one-line errors (exit status 2) instead of the usage and the error."""

    def error(self, message: str) -> NoReturn:
        """Print ``PROG: error: message (see --help)`` and exit with status 2.

        Args:
            message: argparse's description of the problem.
        """
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def add_solver_option(parser: argparse.ArgumentParser) -> None:
    """Add ``--solver`` with graphopt's linear solver names (:data:`graphopt.solvers.SOLVERS`).

    Args:
        parser: The app's parser.
    """
    parser.add_argument(
        "--solver", choices=SOLVERS, default="auto",
        help="linear solver of the reduced camera system (default auto: dense Cholesky for a "
             "small dense system, else CHOLMOD, or iterative-schur — PCG on the implicit Schur "
             "complement — when the explicit one would not fit or be slower)",
    )


def add_stopping_options(parser: argparse.ArgumentParser, iterations: int = 100) -> None:
    """Add ``--iterations`` and the stopping tests of :class:`~graphopt.StoppingConfig`.

    Args:
        parser: The app's parser.
        iterations: The default cap.
    """
    d = StoppingConfig()
    parser.add_argument("-i", "--iterations", type=int, default=iterations, metavar="N",
                        help=f"most iterations (default {iterations}; the run stops earlier "
                             "when a tolerance says it has converged)")
    parser.add_argument("--function-tolerance", type=float, default=d.function_tolerance,
                        metavar="T", help="stop when a step changes chi2 by less than this "
                        f"fraction (default {d.function_tolerance:g}, Ceres'; 0: off)")
    parser.add_argument("--gradient-tolerance", type=float, default=d.gradient_tolerance,
                        metavar="T", help="stop when the gradient's max-norm is below this "
                        f"(default {d.gradient_tolerance:g}; 0: off)")
    parser.add_argument("--parameter-tolerance", type=float, default=d.parameter_tolerance,
                        metavar="T", help="stop when a step is below this fraction of the "
                        f"estimates' norm (default {d.parameter_tolerance:g}; 0: off)")
    parser.add_argument("--gain", type=float, default=0.0, metavar="G",
                        help="g2o's -gain: stop when an iteration decreases chi2 by less than "
                             "this fraction (default 0: off)")


def stopping_config(args: argparse.Namespace) -> StoppingConfig:
    """The :class:`~graphopt.StoppingConfig` of the options :func:`add_stopping_options` added.

    Args:
        args: The parsed arguments.

    Raises:
        AppError: a negative or non-finite tolerance, or a negative iteration count.
    """
    if args.iterations < 0:
        raise AppError(f"--iterations must be >= 0, got {args.iterations}")
    values = {"function_tolerance": args.function_tolerance,
              "gradient_tolerance": args.gradient_tolerance,
              "parameter_tolerance": args.parameter_tolerance, "gain_threshold": args.gain}
    for key, value in values.items():
        if not (math.isfinite(value) and value >= 0):
            flag = "--gain" if key == "gain_threshold" else "--" + key.replace("_", "-")
            raise AppError(f"{flag} must be a finite number >= 0, got {value:g}")
    return StoppingConfig(max_iterations=args.iterations, **values)


def initialize(opt: Any, requested: str) -> tuple[str, str, list[str]]:
    """Initialise an optimizer; name the linear solver that runs.

    A missing CHOLMOD is said in the description (instead of Python's warning).

    Args:
        opt: The :class:`~graphopt.optimizer.SparseOptimizer`.
        requested: The solver name the user asked for.

    Returns:
        ``(name, description, notes)``: the solver that runs (``auto``'s choice, or ``scipy``
        for a missing CHOLMOD), how to say it in a summary, and other warnings' first lines.
    """
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        opt.initialize_optimization()
    notes = [str(w.message).splitlines()[0] for w in caught if "CHOLMOD" not in str(w.message)]
    chosen = getattr(opt.solver, "chosen", None) or opt.solver
    name = str(chosen.name)
    text = name
    if name == "scipy" and requested in ("auto", "cholmod") and not CHOLMOD_AVAILABLE:
        text += " (CHOLMOD's fallback: scikit-sparse is not installed)"
    elif requested == "auto":
        text += " (chosen by auto)"
    return name, text, notes


#: The JSON keys every app writes, with the same meaning: the input, the algorithm, the linear
#: solver that ran and the one asked for, the robust kernel (``"name:delta"`` or ``None``),
#: g2o's chi2 before and after, the iterations that changed the estimate, why the run stopped,
#: and the optimisation's seconds.
COMMON_KEYS = ("input", "algorithm", "solver", "solver_requested", "robust_kernel",
               "initial_chi2", "final_chi2", "iterations", "stop_reason", "seconds",
               "seconds_per_iteration")


def check_run_options(args: argparse.Namespace, robust_delta: float) -> None:
    """Check the options every app has: the stopping options and ``--robust-delta``.

    Args:
        args: The parsed arguments (with :func:`add_stopping_options`' options).
        robust_delta: Robust kernel width (must be finite and positive).

    Raises:
        AppError: Any is out of range.
    """
    stopping_config(args)
    if not math.isfinite(robust_delta) or robust_delta <= 0:
        raise AppError(f"--robust-delta must be positive, got {robust_delta:g}")


def check_outputs(outputs: Mapping[str, str | None], inputs: Sequence[str | None] = ()) -> None:
    """Check output files before any work is done.

    Args:
        outputs: Option name (e.g. ``"--json"``) to the file it names, or None if not given.
        inputs: Input files or folders that no output may overwrite.

    Raises:
        AppError: An output's folder does not exist or is not writable, an output is a
            directory or an input, or two outputs name the same file.
    """
    given = {opt: Path(p) for opt, p in outputs.items() if p is not None}
    protected = {Path(p).resolve() for p in inputs if p is not None}
    for opt, path in given.items():
        folder = path.resolve().parent
        if not folder.is_dir():
            raise AppError(f"{opt} {path}: folder {folder} does not exist")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise AppError(f"{opt} {path}: folder {folder} is not writable")
        if path.is_dir():
            raise AppError(f"{opt} {path}: is a directory")
        if path.resolve() in protected:
            raise AppError(f"{opt} {path}: refusing to overwrite the input")
    if len({p.resolve() for p in given.values()}) != len(given):
        raise AppError("two outputs name the same file")


def _finite_or_none(value: Any) -> Any:
    """``value`` with every non-finite float (at any depth) replaced by None."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {k: _finite_or_none(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite_or_none(v) for v in value]
    return value


def write_json(path: str | os.PathLike[str], data: Mapping[str, Any]) -> None:
    """Write a summary as one indented JSON object, atomically.

    NaN and infinities are written as ``null``, so that the file is valid JSON.

    Args:
        path: Destination file.
        data: The summary (JSON-serialisable values).
    """
    with atomic_write(path) as f:
        json.dump(_finite_or_none(data), f, indent=2, allow_nan=False)
        f.write("\n")


def write_png_image(path: str | os.PathLike[str], image: Any) -> None:
    """Encode an OpenCV image (BGR ``uint8``) as PNG and write it atomically.

    Args:
        path: Destination ``.png`` file.
        image: ``(h, w, 3)`` BGR or ``(h, w)`` grey ``uint8`` array.

    Raises:
        OSError: The encoding failed (the destination is then untouched).
    """
    import cv2  # only the apps that draw need OpenCV

    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"{path}: PNG encoding failed")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())


class RunRecording:
    """A rerun recording of an app run, laid out by :func:`graphopt.recording_view.run_blueprint`.

    The file appears only on :meth:`close` (see :class:`graphopt.recording.Recorder`);
    :meth:`timed` measures the time spent logging, which the apps keep out of the optimisation
    time they report. :meth:`log_metrics` logs the cost (also as log10) and the iteration's
    seconds; :meth:`log_summary` the summary document.

    Args:
        path: Destination ``.rrd`` file.
        prog: The app's name (rerun application id).
        camera_xyz: Camera axis convention (``"RDF"`` or ``"RUB"``).
        world_xyz: World axis convention (a ``rerun.ViewCoordinates`` name).
        blueprint: Keyword arguments of :func:`~graphopt.recording_view.run_blueprint`.
    """

    def __init__(
        self, path: str, prog: str, *, camera_xyz: str, world_xyz: str = "RIGHT_HAND_Z_UP",
        blueprint: Mapping[str, Any] | None = None,
    ) -> None:
        from graphopt.recording import Recorder  # rerun is heavy: only import it when recording
        from graphopt.recording_view import run_blueprint

        self.rec = Recorder(path, application_id=prog, camera_xyz=camera_xyz,
                            world_xyz=world_xyz)
        self.blueprint = dict(blueprint or {})
        self.seconds = 0.0
        #: The last iteration logged (the frame the run's end is shown at), and the last step
        #: (online runs; None otherwise).
        self.iteration = 0
        self.step: int | None = None
        try:
            self.rec.send_blueprint(run_blueprint(**self.blueprint))
            self.rec.name_series("log10_chi2", "log10 chi2", (215, 35, 35))
            self.rec.name_series("chi2", "chi2", (215, 35, 35))
            self.rec.name_series("iteration_seconds", "seconds", (40, 90, 220))
        except BaseException:
            self.rec.abort()
            raise

    def log_metrics(self, iteration: int, chi2: float, seconds: float | None = None,
                    step: int | None = None) -> None:
        """Log the cost (``metrics/chi2`` and ``metrics/log10_chi2``) and the iteration's
        seconds (``metrics/iteration_seconds``) at ``iteration`` (and ``step``).

        Args:
            iteration: Iteration number (0 = before optimisation).
            chi2: The cost after it.
            seconds: The iteration's wall time (None at iteration 0).
            step: The ``step`` timeline's value (online runs), or None.
        """
        self.iteration = max(self.iteration, int(iteration))
        if step is not None:
            self.step = int(step)
            self.rec.set_step(step)
        self.rec.set_iteration(iteration)
        self.rec.log_cost(chi2)
        if seconds is not None:
            self.rec.log_scalar("iteration_seconds", seconds)

    def hide(self, paths: Sequence[str]) -> None:
        """Send the blueprint again with these entities hidden at first (the viewer uses the
        last blueprint sent).

        Args:
            paths: Entity paths, e.g. ``["world/after/outliers"]``.
        """
        from graphopt.recording_view import run_blueprint

        self.blueprint["hidden"] = [*self.blueprint.get("hidden", ()), *paths]
        self.rec.send_blueprint(run_blueprint(**self.blueprint))

    def log_summary(self, markdown: str) -> None:
        """Log the summary document (static: shown at every iteration).

        Args:
            markdown: The text, e.g. from :func:`graphopt.recording_view.summary_markdown`.
        """
        self.rec.log_document(markdown)

    @contextlib.contextmanager
    def timed(self) -> Iterator[Any]:
        """Add the time spent in the ``with`` block to :attr:`seconds`.

        Yields:
            The :class:`graphopt.recording.Recorder`.
        """
        t0 = time.perf_counter()
        try:
            yield self.rec
        finally:
            self.seconds += time.perf_counter() - t0

    def close(self) -> None:
        """Write the recording to its destination."""
        self.rec.close()

    def abort(self) -> None:
        """Discard the recording; an existing destination file is left untouched."""
        self.rec.abort()


#: The signal that interrupted the last optimisation (SIGINT or SIGTERM), else None.
_interrupted: int | None = None


class Terminated(BaseException):
    """SIGTERM outside an optimisation, or a second signal during one: stop at once."""


@contextlib.contextmanager
def _interruptible(opt: Any) -> Iterator[None]:
    """While the block runs, a first SIGINT/SIGTERM asks ``opt`` to stop at its next safe point
    (the run then ends normally, with its outputs); a second one aborts at once."""
    global _interrupted
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    _interrupted = None

    def handler(signum: int, frame: Any) -> None:
        global _interrupted
        if _interrupted is None:
            _interrupted = signum
            opt.stop()
            return
        raise KeyboardInterrupt if signum == signal.SIGINT else Terminated()

    previous = {s: signal.signal(s, handler) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def optimize_recorded(opt: Any, iterations: int, recording: RunRecording | None) -> Any:
    """``opt.optimize(iterations)``, interruptible, discarding the recording if it raises.

    A first Ctrl-C (or SIGTERM) ends the optimisation at the next safe point with the stop
    reason ``interrupted``: the app then writes its outputs from the best estimate and
    :func:`run_main` exits with 130 (143). A second one aborts at once.

    Args:
        opt: The :class:`graphopt.SparseOptimizer`.
        iterations: Maximum iterations.
        recording: The run's recording, or None.

    Returns:
        The optimisation result.
    """
    try:
        with _interruptible(opt):
            return opt.optimize(iterations)
    except BaseException:
        if recording is not None:
            recording.abort()
        raise


def run_main(
    prog: str,
    parser: argparse.ArgumentParser,
    run: Callable[[argparse.Namespace], Any],
    argv: Sequence[str] | None,
    user_errors: tuple[type[BaseException], ...] = (),
) -> int:
    """Parse the arguments, run the app and turn errors into one line on stderr.

    Args:
        prog: The app's name, the prefix of every message.
        parser: The app's parser.
        run: The app; it receives the parsed arguments.
        argv: Arguments (``sys.argv[1:]`` if None).
        user_errors: Further exception types whose message is meant for the user (besides
            :class:`AppError` and ``OSError``).

    Returns:
        Exit status: 0 on success, 1 on an error, 130 on Ctrl-C (2 for bad options, by the
        parser's ``SystemExit``). With the environment variable ``GRAPHOPT_DEBUG`` set, an
        unexpected exception propagates with its traceback.
    """
    global _interrupted
    args = parser.parse_args(argv)
    _interrupted = None
    main_thread = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminate) if main_thread else None
    try:
        run(args)
    except (AppError, OSError, *user_errors) as exc:
        print(f"{prog}: error: {_first_line(exc)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted; no output written", file=sys.stderr)
        return 130
    except Terminated:
        print(f"{prog}: terminated; no output written", file=sys.stderr)
        return 143
    except Exception as exc:  # noqa: BLE001 - the user gets one line, not a traceback
        if os.environ.get("GRAPHOPT_DEBUG"):
            raise
        print(f"{prog}: error: {type(exc).__name__}: {_first_line(exc)}", file=sys.stderr)
        return 1
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    if _interrupted is not None:
        name = "interrupted" if _interrupted == signal.SIGINT else "terminated"
        print(f"{prog}: {name}: the outputs were written from the best estimate",
              file=sys.stderr)
        return 128 + int(_interrupted)
    return 0


def _terminate(signum: int, frame: Any) -> None:
    """SIGTERM outside an optimisation: stop at once (outputs are written atomically, so none
    is left half-written)."""
    raise Terminated()


def _first_line(exc: BaseException) -> str:
    """The first line of an exception's message."""
    text = str(exc)
    return text.splitlines()[0] if text else ""
