"""What the commands show while they work: log lines, rich progress bars with an ETA, `run.log`.

The workflow functions (`run_fit`, `run_diagnose`, `run_sensitivity`, `run_tune`) take a `log=`
callable and stay usable with `print`, `None` or any function of one string. The commands pass a
`RunLog`, which is such a callable with one more method, `task`, that opens a progress bar. Code
that wants a bar asks for one with `task(log, ...)`, which gives a do-nothing stand-in when `log`
is not a `RunLog`; so the library never depends on a terminal.

Work in compiled programs reports from Python between calls, never through a host callback inside
them (JAX's persistent compilation cache refuses such programs): `hdjax._fit.least_squares.fit_parameters` steps
its Levenberg–Marquardt loop from Python and reports each step, `fit_per_experiment` reports
after each chunk of experiments. `current()` is the `RunLog` of the command running in this
thread, if any.
"""

import contextlib
import contextvars
import pathlib
import sys
import threading
import time
from typing import Any

_CURRENT: contextvars.ContextVar = contextvars.ContextVar("hdjax_runlog", default=None)


def current():
    """The `RunLog` of the command running in this context, or None (library use)."""
    return _CURRENT.get()


class _NullTask:
    """Stand-in for `Task` when nothing shows progress."""

    def advance(self, n: int | float = 1, *, info: str | None = None, line: str | None = None) -> None:
        pass

    def update(self, *, total: int | float | None = None, info: str | None = None) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


class Task:
    """One progress bar of a `RunLog` (a context manager; the bar goes when the block ends and a
    one-line summary is logged). `advance` may be called from any thread (JAX callbacks)."""

    def __init__(self, runlog: "RunLog", description: str, total: int | float | None, unit: str):
        self._log = runlog
        self.description = description
        self.total = total
        self.unit = unit
        self.completed = 0.0
        self._id = None
        self._t0 = time.time()

    def __enter__(self):
        self._t0 = time.time()
        self._id = self._log._add(self)
        return self

    def advance(self, n: int | float = 1, *, info: str | None = None, line: str | None = None) -> None:
        """Count `n` more units done; `info` replaces the text shown beside the bar; `line` goes to
        run.log only (a detail not worth a screen line)."""
        self.completed += n
        if self.total is not None and self.completed > self.total:
            self.total = self.completed
        self._log._refresh(self, info)
        if line is not None:
            self._log._write(line)

    def update(self, *, total: int | float | None = None, info: str | None = None) -> None:
        """Change the expected total or the text beside the bar."""
        if total is not None:
            self.total = max(total, self.completed)
        self._log._refresh(self, info)

    def __exit__(self, *exc):
        self._log._remove(self)
        done = f"{self.completed:g}" + (f"/{self.total:g}" if self.total is not None else "")
        self._log._write(f"      {self.description}: {done} {self.unit} in {time.time() - self._t0:.1f} s")
        return False


class RunLog:
    """The `log` of a command: `runlog(line)` prints the line (unless `quiet`) and appends it to
    `path` (run.log); `runlog.task(description, total)` opens a rich progress bar with an ETA (shown
    only on a terminal and unless `quiet`).

    Use as a context manager: inside the block it is `current()`, so that compiled loops deep in
    the library report to it.

    The class stays long (about 125 lines) on purpose: its methods are short and share one lock,
    one run.log file and one progress display, which splitting it would scatter."""

    def __init__(self, *, quiet: bool = False, path: str | pathlib.Path | None = None, console=None):
        self.quiet = quiet
        self.path = None if path is None else pathlib.Path(path)
        self._file = None
        self._lock = threading.RLock()
        self._console = console
        self._progress = None
        self._token = None

    # -- context ------------------------------------------------------------------------------
    def __enter__(self):
        if self.path is not None:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "w", encoding="utf-8")  # noqa: SIM115 (closed in __exit__)
            self._write(f"# hdjax run started {time.strftime('%Y-%m-%d %H:%M:%S')}")
        self._token = _CURRENT.set(self)
        return self

    def __exit__(self, *exc):
        if self._token is not None:
            _CURRENT.reset(self._token)
            self._token = None
        with self._lock:
            if self._progress is not None:
                self._progress.stop()
                self._progress = None
            if self._file is not None:
                self._file.close()
                self._file = None
        return False

    # -- lines --------------------------------------------------------------------------------
    @property
    def console(self):
        if self._console is None:
            from rich.console import Console

            self._console = Console(highlight=False, soft_wrap=True)
        return self._console

    def __call__(self, *parts) -> None:
        line = " ".join(str(p) for p in parts)
        self._write(line)
        if not self.quiet:
            with self._lock:
                self.console.print(line, markup=False, highlight=False)

    def error(self, line: str) -> None:
        """A line for stderr (always shown) and run.log."""
        self._write(line)
        print(line, file=sys.stderr)

    def warning(self, line: str) -> None:
        """A line for stderr (unless quiet) and run.log: input that was accepted but partly ignored."""
        self._write(line)
        if not self.quiet:
            print(line, file=sys.stderr)

    def _write(self, line: str) -> None:
        with self._lock:
            if self._file is not None:
                self._file.write(f"{time.strftime('%H:%M:%S')} {line}\n")
                self._file.flush()

    # -- progress -----------------------------------------------------------------------------
    @property
    def shows_bars(self) -> bool:
        return not self.quiet and self.console.is_terminal

    def task(self, description: str, total: int | float | None = None, *, unit: str = "steps") -> Task:
        """A progress bar for `total` units of work (None: unknown, a spinner with elapsed time)."""
        return Task(self, description, total, unit)

    def _add(self, task: Task):
        if not self.shows_bars:
            return None
        with self._lock:
            if self._progress is None:
                from rich.progress import (
                    BarColumn,
                    MofNCompleteColumn,
                    Progress,
                    SpinnerColumn,
                    TextColumn,
                    TimeElapsedColumn,
                    TimeRemainingColumn,
                )

                self._progress = Progress(
                    SpinnerColumn(),
                    TextColumn("{task.description}"),
                    BarColumn(bar_width=28),
                    MofNCompleteColumn(),
                    TextColumn("{task.fields[info]}"),
                    TextColumn("elapsed"),
                    TimeElapsedColumn(),
                    TextColumn("ETA"),
                    TimeRemainingColumn(),
                    console=self.console,
                    transient=True,
                )
                self._progress.start()
            return self._progress.add_task(f"      {task.description}", total=task.total, info="")

    def _refresh(self, task: Task, info: str | None) -> None:
        if task._id is None or self._progress is None:
            return
        with self._lock:
            kw: dict[str, Any] = {} if info is None else {"info": info}
            self._progress.update(task._id, completed=task.completed, total=task.total, **kw)

    def _remove(self, task: Task) -> None:
        if task._id is None or self._progress is None:
            return
        with self._lock:
            self._progress.remove_task(task._id)
            if not self._progress.tasks:
                self._progress.stop()
                self._progress = None


def task(log, description: str, total: int | float | None = None, *, unit: str = "steps"):
    """A progress bar on `log` when it is a `RunLog` (else on the command's `current()` one when
    `log` is None), otherwise a do-nothing stand-in. Use as `with task(log, "fits", n) as t: ...`."""
    target = log if isinstance(log, RunLog) else (current() if log is None else None)
    if target is None:
        return _NullTask()
    return target.task(description, total, unit=unit)


@contextlib.contextmanager
def lm_progress(description: str, max_steps: int, log=None):
    """For `hdjax._fit.least_squares`: yields a function `(step, cost, gn_step_in_se)`, called after each LM
    step, that advances a bar of `max_steps` LM steps (ETA: an upper bound, LM usually stops
    earlier), or None when no `RunLog` is listening."""
    target = log if isinstance(log, RunLog) else current()
    if target is None:
        yield None
        return
    with target.task(description, max_steps, unit="LM steps") as t:
        def callback(step, cost, gn_step):
            t.advance(1, info=f"½χ² {float(cost):.6g}, Gauss–Newton step {float(gn_step):.2g} SE",
                      line=f"        LM step {int(step)}: ½χ² {float(cost):.8g}, "
                           f"Gauss–Newton step {float(gn_step):.3g} SE")

        yield callback


@contextlib.contextmanager
def count_progress(description: str, total: int, *, unit: str, log=None):
    """For work done item by item: yields a function `(*values)` that advances a bar of `total`
    items by one, or None when no `RunLog` is listening."""
    target = log if isinstance(log, RunLog) else current()
    if target is None:
        yield None
        return
    with target.task(description, total, unit=unit) as t:
        yield lambda *_: t.advance(1)
