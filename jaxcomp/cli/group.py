"""The ``jaxcomp`` command group and its entry point; each command lives in its own module."""

import sys

import click

from jaxcomp.errors import JaxcompError


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="jaxcomp")
def cli() -> None:
    """jaxcomp: compliant control of current-controlled arms without torque sensors.

    Identify each joint's current/torque ratio, friction loss and the centre-of-mass errors of
    the robot model from slow gravity-loaded sweeps, then drive the arm with a current-based
    Cartesian impedance controller. Units are SI throughout (m, rad, N m, A) unless a column
    says deg.
    """


def _compilation_cache() -> None:
    """Keep compiled XLA programs between runs (``$JAXCOMP_CACHE``, default
    ``~/.cache/jaxcomp/xla``; ``JAXCOMP_CACHE=off`` disables it): the fits and the controller
    compile for seconds and then run in milliseconds."""
    import os
    from pathlib import Path

    where = os.environ.get("JAXCOMP_CACHE", str(Path.home() / ".cache" / "jaxcomp" / "xla"))
    if where.lower() in ("off", "0", "none", ""):
        return
    import jax

    jax.config.update("jax_compilation_cache_dir", where)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)


def _lapack_threads() -> None:
    """One thread for scipy's OpenBLAS (not loaded yet; JAX's CPU backend calls its LAPACK):
    the fits' matrices are small, and OpenBLAS's idle threads spin, taking a core from the work
    (0.6 s of CPU in a 32-recording ``fit --each`` on 2 cores). ``OPENBLAS_NUM_THREADS`` that
    the user sets wins."""
    import os

    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def _device_memory() -> None:
    """Take GPU memory as it is needed instead of JAX's default 75 % of the card at start-up:
    on an 80 GB H100 that preallocation alone holds 1.9 GB of host memory (a process's RSS
    2.6 GB after its first array, 0.7 GB without). ``XLA_PYTHON_CLIENT_PREALLOCATE`` or
    ``XLA_PYTHON_CLIENT_MEM_FRACTION`` that the user sets wins."""
    import os

    if "XLA_PYTHON_CLIENT_MEM_FRACTION" not in os.environ:
        os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")


def main() -> None:
    """Entry point: run the CLI; jaxcomp's own errors, and a file that cannot be read or
    written (``OSError``: read-only, full disk), print one ``error:`` line, status 2."""
    _device_memory()
    _compilation_cache()
    _lapack_threads()
    try:
        cli(standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("aborted", err=True)
        sys.exit(130)
    except click.ClickException as exc:
        exc.show()
        sys.exit(exc.exit_code)
    except JaxcompError as exc:
        click.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except OSError as exc:
        from jaxcomp.files import file_problem

        click.echo(f"error: {file_problem(exc)}", err=True)
        sys.exit(2)
