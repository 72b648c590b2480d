"""`jaxcomp bench`: run the benchmarks of experiments/ and gather them into one report.

Each benchmark is a script of a jaxcomp checkout's ``experiments/`` folder that writes its
figures to a JSON file (``--json``); this command runs them one after the other in fresh
processes (so each one compiles and allocates as it would alone), then writes
``bench.json`` (the machine and every benchmark's figures) and ``bench.md`` (one table per
benchmark) into the output folder, after every benchmark, atomically.
"""

from __future__ import annotations

import datetime
import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import click

from jaxcomp.cli.group import cli
from jaxcomp.errors import InputError


@dataclass(frozen=True)
class Benchmark:
    """One script of experiments/: what it measures, its arguments in full and --quick runs
    (``{gpu}`` entries are chosen by whether the machine has a GPU).

    Attributes:
        script: the script's file name in experiments/.
        measures: what it measures and its targets, one line of the report.
        full: its arguments for a full run.
        quick: its arguments for a ``--quick`` run.
        gpu: its arguments for a full run on a machine with a GPU (None: ``full``).
    """

    script: str
    measures: str
    full: tuple[str, ...] = ()
    quick: tuple[str, ...] = ()
    gpu: tuple[str, ...] | None = None  # full arguments on a machine with a GPU


BENCHMARKS: dict[str, Benchmark] = {
    "dynamics": Benchmark(
        "bench_dynamics.py",
        "dynamics: one jitted gravity + Jacobian + mass matrix call vs pinocchio (target: median"
        " <= 40 us, p99 <= 150 us); vmapped gravity poses/s (target >= 1e6)",
        quick=("--repeats", "300", "--poses", "2000"),
    ),
    "sim": Benchmark(
        "bench_sim.py",
        "simulator: lock-step speed in multiples of real time (target >= 20x)",
        quick=("--seconds", "0.5", "--repeats", "1"),
    ),
    "fit": Benchmark(
        "bench_fit.py",
        "fit: one ~230 000-sample recording fitted (target <= 1 s); --each batch vs the scipy loop",
        quick=("--count", "4", "--scipy-count", "1", "--pool", "4"),
    ),
    "control": Benchmark(
        "bench_control.py",
        "controller: jitted step vs pinocchio + numpy (target: median <= 50 us, p99 <= 150 us)",
        quick=("--repeats", "300", "--block", "100"),
    ),
    "loop": Benchmark(
        "bench_loop.py",
        "control loop: 1 kHz in lock step (target >= 5x real time) and paced to the wall clock "
        "for 60 s (target < 0.1 % missed deadlines)",
        full=("--repeats", "3", "--realtime", "60"),
        quick=("--repeats", "1"),
    ),
    "console": Benchmark(
        "bench_console.py",
        "browser console: the 1 kHz loop of the mobile robot paced for 60 s with the console "
        "and a headless browser attached, and without (target < 0.1 % missed deadlines, no more "
        "than without)",
        full=("--seconds", "60", "--repeats", "2"),
        quick=("--seconds", "3"),
    ),
    "mjx": Benchmark(
        "bench_mjx.py",
        "MJX: world-steps/s of a batched sweep plan, float64 (target >= 5e6 on one GPU)",
        full=("--worlds", "64", "--steps", "1000"),
        quick=("--worlds", "2", "--steps", "50", "--settle", "10"),
        gpu=("--worlds", "32768", "--steps", "2000", "--every", "10"),
    ),
}


def default_experiments() -> Path:
    """The experiments/ folder of the checkout this package was installed from (editable)."""
    return Path(__file__).resolve().parents[2] / "experiments"


def machine() -> dict:
    """CPU, cores, memory, OS, Python, JAX and its devices (asked of a child process, so this
    process never takes GPU memory away from the benchmarks)."""
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info = {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "os": platform.platform(),
        "python": platform.python_version(),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    try:
        mem = Path("/proc/meminfo").read_text().split()
        info["memory_gib"] = round(int(mem[mem.index("MemTotal:") + 1]) / 2**20, 1)
    except (OSError, ValueError, IndexError):
        pass
    probe = (
        "import json, jax; d = jax.devices(); print(json.dumps({'jax': jax.__version__, "
        "'backend': jax.default_backend(), 'devices': [x.device_kind for x in d]}))"
    )
    env = dict(os.environ, XLA_PYTHON_CLIENT_PREALLOCATE="false")
    try:
        out = subprocess.run(
            [sys.executable, "-c", probe], capture_output=True, text=True, env=env, timeout=120
        )
        info.update(json.loads(out.stdout.strip().splitlines()[-1]))
    except (subprocess.SubprocessError, ValueError, IndexError):
        info["jax"] = "unavailable"
    return info


def _flatten(figures: dict, prefix: str = "") -> list[tuple[str, object]]:
    rows: list[tuple[str, object]] = []
    for key, value in figures.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            rows += _flatten(value, f"{name} / ")
        else:
            rows.append((name, value))
    return rows


def _cell(value: object) -> str:
    if isinstance(value, bool) or value is None:
        return str(value)
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, list):
        return ", ".join(_cell(v) for v in value)
    return str(value)


def markdown(report: dict) -> str:
    """The report as markdown: the machine, then one table of figures per benchmark.

    Args:
        report: {"machine": ``machine()``, "mode": "quick"|"full", "benchmarks": {name:
            ``run_benchmark`` entry}}.

    Returns:
        The markdown text, ending in a newline.
    """
    m = report["machine"]
    lines = [
        "# jaxcomp benchmarks",
        "",
        f"{m.get('date', '')}: {m.get('cpu', '?')}, {m.get('cores', '?')} cores, "
        f"{m.get('memory_gib', '?')} GiB; {m.get('os', '')}; Python {m.get('python', '')}, "
        f"JAX {m.get('jax', '?')} ({m.get('backend', '?')}: "
        f"{', '.join(m.get('devices', [])) or '-'}); mode: {report['mode']}",
    ]
    for name, entry in report["benchmarks"].items():
        lines += ["", f"## {name}", "", entry["measures"], ""]
        lines.append(
            f"`python experiments/{entry['script']} {' '.join(entry['args'])}` "
            f"({entry['seconds']:.0f} s, {entry['status']})"
        )
        if entry["status"] != "ok":
            lines += ["", "```", entry.get("error", ""), "```"]
            continue
        lines += ["", "| figure | value |", "| --- | ---: |"]
        lines += [f"| {k} | {_cell(v)} |" for k, v in _flatten(entry["figures"])]
    return "\n".join(lines) + "\n"


def run_benchmark(
    bench: Benchmark, folder: Path, args: list[str], log: Path, timeout: float
) -> dict:
    """Run one script with ``--json``; its figures, or the reason it failed.

    Args:
        bench: the benchmark.
        folder: the experiments/ folder holding its script.
        args: the script's arguments (without ``--json``).
        log: file for its stdout and stderr; its figures go to this path with .json.
        timeout: seconds it may run before it is stopped.

    Returns:
        {"script", "measures", "args", "seconds": wall time s, "status": "ok" or "failed
        (why)"}, with "figures" (its JSON) when ok, else "error" (its output's last 15 lines).
    """
    from jaxcomp.robot_params import write_text_atomic

    result_file = log.with_suffix(".json")
    result_file.unlink(missing_ok=True)
    cmd = [sys.executable, str(folder / bench.script), *args, "--json", str(result_file)]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        output, code = proc.stdout + proc.stderr, proc.returncode
    except subprocess.TimeoutExpired as exc:
        output = (exc.stdout or b"").decode() if isinstance(exc.stdout, bytes) else exc.stdout
        output, code = (output or "") + f"\n(stopped after {timeout:g} s)", None
    entry = {
        "script": bench.script,
        "measures": bench.measures,
        "args": args,
        "seconds": time.perf_counter() - t0,
    }
    write_text_atomic(log, output)
    if code == 0 and result_file.exists():
        entry.update(status="ok", figures=json.loads(result_file.read_text()))
    else:
        tail = "\n".join(output.strip().splitlines()[-15:])
        why = "timed out" if code is None else f"exit status {code}"
        entry.update(status=f"failed ({why})", error=tail)
    return entry


@cli.command()
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("bench"),
    show_default=True,
    help="Folder for bench.json, bench.md and each benchmark's output log.",
)
@click.option(
    "--only",
    multiple=True,
    type=click.Choice(list(BENCHMARKS)),
    help="Run only these benchmarks (repeatable); default: all.",
)
@click.option(
    "--quick",
    is_flag=True,
    help="Small sizes (seconds each, not minutes): checks that every benchmark runs; its "
    "figures are not the targets' measurements.",
)
@click.option(
    "--experiments",
    "folder",
    type=click.Path(file_okay=False, path_type=Path),
    default=None,
    help="The experiments/ folder of a jaxcomp checkout; default: the one this package was "
    "installed from.",
)
@click.option(
    "--timeout",
    type=float,
    default=1800.0,
    show_default=True,
    help="Seconds one benchmark may run before it is stopped and reported as failed.",
)
def bench(
    out_dir: Path, only: tuple[str, ...], quick: bool, folder: Path | None, timeout: float
) -> None:
    """Run every benchmark and write one report (markdown table and JSON).

    Each benchmark runs in its own process, one after another, with its figures taken from
    its --json output; the report names the machine (CPU, cores, memory, JAX backend and
    devices). On a machine with a GPU the MJX benchmark runs 32 768 worlds. Exit status 1 if a
    benchmark failed (the report says which and why).
    """
    from tqdm.auto import tqdm

    from jaxcomp.robot_params import write_json_atomic, write_text_atomic

    folder = folder or default_experiments()
    names = list(only) or list(BENCHMARKS)
    missing = [BENCHMARKS[n].script for n in names if not (folder / BENCHMARKS[n].script).exists()]
    if missing:
        raise InputError(
            f"no benchmark script {', '.join(missing)} in {folder}: pass --experiments DIR, the "
            "experiments/ folder of a jaxcomp checkout"
        )
    if timeout <= 0:
        raise InputError(f"--timeout must be > 0 s, got {timeout:g}")
    info = machine()
    has_gpu = info.get("backend") in ("gpu", "cuda", "rocm")
    report = {"machine": info, "mode": "quick" if quick else "full", "benchmarks": {}}
    logs = out_dir / "logs"
    logs.mkdir(parents=True, exist_ok=True)
    bar = tqdm(names, desc="benchmarks", unit="bench")
    for name in bar:
        bar.set_postfix_str(name)
        b = BENCHMARKS[name]
        args = b.quick if quick else (b.gpu if has_gpu and b.gpu is not None else b.full)
        entry = run_benchmark(b, folder, list(args), logs / f"{name}.txt", timeout)
        report["benchmarks"][name] = entry
        write_json_atomic(out_dir / "bench.json", report)
        write_text_atomic(out_dir / "bench.md", markdown(report))
        if entry["status"] != "ok":
            tqdm.write(f"{name}: {entry['status']} (log: {logs / f'{name}.txt'})")
    click.echo(f"wrote {out_dir / 'bench.md'} and {out_dir / 'bench.json'}")
    if any(e["status"] != "ok" for e in report["benchmarks"].values()):
        sys.exit(1)
