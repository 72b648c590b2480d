"""`jaxcomp bench`: runs the experiments/ benchmarks in child processes, one report."""

import json

from click.testing import CliRunner

from jaxcomp.cli import cli


def test_bench_quick_writes_the_figures_of_each_benchmark(tmp_path):
    out = tmp_path / "report"
    res = CliRunner().invoke(cli, ["bench", "--quick", "--only", "sim", "--out", str(out)])
    assert res.exit_code == 0, res.output
    report = json.loads((out / "bench.json").read_text())
    assert report["machine"]["cores"] >= 1 and report["machine"]["jax"] != "unavailable"
    sim = report["benchmarks"]["sim"]
    assert sim["status"] == "ok" and list(report["benchmarks"]) == ["sim"]
    speeds = sim["figures"]["x_realtime"]
    assert len(speeds) == 3 and all(v["median"] > 1.0 for v in speeds.values())
    md = (out / "bench.md").read_text()
    assert "## sim" in md and "| x_realtime / bare physics step" in md
    assert "bench_sim.py --seconds 0.5 --repeats 1" in md
    assert "x real time, 1 runs of 0.5 s" in (out / "logs" / "sim.txt").read_text()


def test_bench_reports_a_failing_benchmark_and_exits_1(tmp_path):
    folder = tmp_path / "experiments"
    folder.mkdir()
    (folder / "bench_sim.py").write_text("import sys\nprint('boom: no simulator')\nsys.exit(3)\n")
    out = tmp_path / "report"
    args = ["bench", "--only", "sim", "--experiments", str(folder), "--out", str(out)]
    res = CliRunner().invoke(cli, args)
    assert res.exit_code == 1
    entry = json.loads((out / "bench.json").read_text())["benchmarks"]["sim"]
    assert entry["status"] == "failed (exit status 3)" and "boom: no simulator" in entry["error"]
    assert "boom: no simulator" in (out / "bench.md").read_text()


def test_bench_without_the_scripts_names_the_folder(tmp_path):
    res = CliRunner().invoke(cli, ["bench", "--experiments", str(tmp_path), "--out", "x"])
    assert res.exit_code != 0
    assert "no benchmark script bench_dynamics.py" in str(res.exception)
    assert str(tmp_path) in str(res.exception)
