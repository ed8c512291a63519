"""The ``orthowarp`` command line: parses, calls the public API, reports.

Library errors become one-line messages on stderr and a non-zero exit code. Each command lives
in its own module and imports the library inside its function, so that ``orthowarp --help``
loads only click; the options several commands share are declared once, in
:mod:`orthowarp.cli.options`.
"""

from __future__ import annotations

import faulthandler
import logging
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable
from typing import Any, NoReturn

import click

from ..errors import OrthowarpError, OrthowarpWarning
from . import adjust, demo, match, mosaic, ortho, spot_adjust
from .warm import start_cuda_driver

__all__ = ["main"]


class _Group(click.Group):
    """Run a command so that it can be stopped cleanly, and report its end: library errors
    become a one-line message and exit code 1; SIGINT and SIGTERM a clean stop with exit code
    130 or 143.

    The command runs in a worker thread. A signal only sets the event
    ``ctx.meta["orthowarp.stop"]``, which the commands pass to the library as ``cancel``: the
    ortho stops before its next tile, and nothing is published. The main thread waits; if the
    command has not ended ``STOP_GRACE`` seconds after the signal (a stage that does not look
    at the event), or at a second signal, it removes this process's temporaries and exits at
    once. No exception is ever raised asynchronously into library code (where it could leave
    a lock held)."""

    STOP_GRACE = 10.0

    def invoke(self, ctx: click.Context) -> Any:
        shown = warnings.showwarning

        def show(message, category, *args, **kwargs):  # the library's warnings as one line each
            if issubclass(category, OrthowarpWarning):
                click.echo(f"Warning: {message}", err=True)
            else:
                shown(message, category, *args, **kwargs)

        warnings.showwarning = show
        try:
            return self._invoke(ctx)
        finally:
            warnings.showwarning = shown

    def _invoke(self, ctx: click.Context) -> Any:
        stop = ctx.meta["orthowarp.stop"] = threading.Event()
        if threading.current_thread() is not threading.main_thread():  # no signals: run here
            return self._report(lambda: super(_Group, self).invoke(ctx))
        outcome, received = {}, []

        def work():
            try:
                outcome["value"] = super(_Group, self).invoke(ctx)
            except BaseException as e:  # handed to the main thread
                outcome["error"] = e

        def handle(signum, frame):
            if received:
                _exit_now(signum)
            received.append((signum, time.monotonic()))
            stop.set()

        previous = {sig: signal.signal(sig, handle) for sig in (signal.SIGINT, signal.SIGTERM)}
        try:
            worker = threading.Thread(target=work, name="orthowarp-command")
            worker.start()
            while worker.is_alive():
                worker.join(0.1)
                if received and time.monotonic() - received[0][1] > self.STOP_GRACE:
                    _exit_now(received[0][0])
        finally:
            for sig, handler in previous.items():
                signal.signal(sig, handler)
        if received:
            terminated = received[0][0] == signal.SIGTERM
            click.echo(f"Error: {'terminated' if terminated else 'interrupted'}; no output was left half-written",
                       err=True)
            sys.exit(128 + received[0][0])

        def result():
            if "error" in outcome:
                raise outcome["error"]
            return outcome.get("value")

        return self._report(result)

    @staticmethod
    def _report(call: Callable[[], Any]) -> Any:
        try:
            return call()
        except OrthowarpError as e:
            click.echo(f"Error: {e}", err=True)
            sys.exit(1)
        except KeyboardInterrupt:
            click.echo("Error: interrupted; no output was left half-written", err=True)
            sys.exit(128 + signal.SIGINT)


def _exit_now(signum: int) -> NoReturn:
    """Last resort of a stop: remove the temporaries, exit without waiting for anything."""
    from ..pipeline.raster.io import remove_own_temporaries

    remove_own_temporaries()
    sys.stderr.write(f"Error: stopped by signal {signum}; temporaries removed\n")
    sys.stderr.flush()
    os._exit(128 + signum)


def _enable_faulthandler() -> None:
    """A crash in native code (GDAL, the CUDA driver, Warp's kernels) prints every thread's
    Python stack on stderr before the process dies, so that the report says where it was
    (where stderr is a real file: not under click's test runner)."""
    if faulthandler.is_enabled():
        return
    try:
        faulthandler.enable(all_threads=True)
    except (AttributeError, OSError, ValueError):  # no file descriptor behind sys.stderr
        pass


@click.group(cls=_Group)
@click.version_option(package_name="orthowarp")
@click.option("-v", "--verbose", count=True,
              help="More log output, Warp's own messages included (-vv for debug).")
@click.option("-q", "--quiet", is_flag=True, help="Only errors; no progress bars.")
@click.pass_context
def main(ctx: click.Context, verbose: int, quiet: bool) -> None:
    """orthowarp: rigorous orthorectification on the GPU with NVIDIA Warp."""
    _enable_faulthandler()
    start_cuda_driver(ctx.invoked_subcommand)
    import warp as wp

    from .._device import set_warp_messages

    ctx.obj = {"quiet": quiet}
    level = logging.ERROR if quiet else (logging.DEBUG if verbose > 1 else logging.INFO if verbose else logging.WARNING)
    logging.basicConfig(level=level, format="%(levelname)s %(name)s: %(message)s")
    # Dask's own log (set up by Dask when it is imported, here and in the workers of a cluster
    # this command starts): its warnings with -v, its messages with -vv, else nothing (a
    # failure of the run is this command's error message)
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "info" if verbose > 1 and not quiet else
                          "warning" if verbose and not quiet else "critical")
    # Warp's banner, module-load lines and driver notices only with -v; the library keeps them
    # quiet during its calls, and this process is the CLI's own, so its Warp level is set too.
    show = bool(verbose) and not quiet
    set_warp_messages(show)
    if show and hasattr(wp, "LOG_INFO") and wp.config.log_level > wp.LOG_INFO:
        wp.config.log_level = wp.LOG_INFO
    elif not show:
        if hasattr(wp, "LOG_WARNING"):
            wp.config.log_level = wp.LOG_WARNING
        else:  # warp-lang < 1.10
            wp.config.quiet = True


for _command in (demo.demo, ortho.ortho, mosaic.mosaic, adjust.adjust, spot_adjust.spot_adjust, match.match):
    main.add_command(_command)
