"""experiments.bench's report: the committed tables are what the committed code renders from the
committed figures, a partial run renders the rows it measured, the GPU run made the CPU run's
decisions, and a wrong option is refused before anything loads."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from experiments import bench

RESULTS = Path(__file__).resolve().parent.parent / "results" / "bench"
NAMES = ("bench_cpu", "bench_gpu", "bench_gpu_hull")


def _figures(name: str) -> dict:
    return json.loads((RESULTS / f"{name}.json").read_text())


@pytest.mark.parametrize("name", NAMES)
def test_committed_table_is_rendered_from_committed_figures(name):
    assert bench.markdown(_figures(name)) == (RESULTS / f"{name}.md").read_text()


def test_gpu_runs_made_the_cpu_runs_decisions():
    """Every Stage B method the GPU measured certified the same trajectories with the same number of
    evaluations each as on the CPU (equal decisions_sha256)."""
    cpu = _figures("bench_cpu")["stageB"]
    compared = 0
    for name in ("bench_gpu", "bench_gpu_hull"):
        gpu = _figures(name)
        assert gpu["machine"]["device"].startswith("cuda")
        for enc, run in gpu["stageB"].items():
            for method in ("larc", "fine"):
                assert run[method]["decisions_sha256"] == cpu[enc][method]["decisions_sha256"], (name, enc, method)
                compared += 1
    assert compared == 4  # both enclosures, both methods


def _run(evals: int, certified: int, paired: bool) -> dict:
    method = {"certified": certified, "evaluations": evals, "warm_s": 0.5, "compile_s": 3.0,
              "intervals_per_s": evals / 0.5, "pairs_per_s": 40 * evals / 0.5}
    out = {"n_trajectories": 7, "larc": dict(method), "fine": dict(method, evaluations=3 * evals, warm_s=1.0),
           "fine_over_larc_time": 2.0, "fine_over_larc_evaluations": 3.0}
    if paired:
        out["paired"] = {"larc_median_ms": 2.0, "fine_median_ms": 3.0, "median_fine_over_larc": 1.5,
                         "tree_median_ms": 1.25, "median_fine_over_tree": 2.4}
    return out


@pytest.mark.parametrize("encs", [("capsules",), ("hull",), ("capsules", "hull")])
@pytest.mark.parametrize("paired", [True, False])
def test_partial_run_renders_what_it_measured(encs, paired):
    out = {"machine": {"device": "cuda:0", "cores": 16},
           "stageB": {e: _run(100 + k, 5 + k, paired) for k, e in enumerate(encs)}}
    text = bench.markdown(out)
    header = next(line for line in text.splitlines() if line.startswith("| | "))
    assert header.count("LARC") == len(encs) and header.count("fine") == len(encs)
    assert ("cascade: LARC" in header) == ("hull" in encs) and ("capsules: LARC" in header) == ("capsules" in encs)
    assert ("one trajectory per call" in text) == paired
    assert ("LARC on the device tree" in text and "1.25 ms" in text and "2.40×" in text) == paired
    assert ("The cascade costs LARC" in text) == (len(encs) == 2)
    assert "kernel (XLA" not in text and "Streaming" not in text  # sections it did not measure
    widths = {line.count("|") for line in text.splitlines() if line.startswith("| ") and "capsules: LARC" not in line
              and "cascade: LARC" not in line and "fine / LARC" not in line}
    assert widths <= {2 * len(encs) + 2, len(encs) + 3}  # every row has its table's columns


def test_wrong_enclosure_refused_before_loading(capsys):
    with pytest.raises(SystemExit) as e:
        bench.main(["--enclosures", "capsules,hul", "--stageB-only"])
    assert e.value.code == 2
    assert "'hul' is not one of capsules, hull" in capsys.readouterr().err


def test_later_sections_need_the_capsule_run(capsys):
    """The kernel, reference and audit sections compare with the capsule run: without it, only the
    Stage B section may run."""
    with pytest.raises(SystemExit) as e:
        bench.main(["--enclosures", "hull"])
    assert e.value.code == 2 and "needs --stageB-only" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["--render"], ["--render", "--json", "no/such/bench.json"]])
def test_render_needs_its_figures(argv, capsys):
    with pytest.raises(SystemExit) as e:
        bench.main(argv)
    assert e.value.code == 2 and "--render needs --json FILE" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["tree_cpu", "tree_cpu1"])
def test_device_tree_table_is_rendered_and_agrees(name):
    """experiments.bench_tree's committed tables render from their figures, and the device tree made
    the host frontier's evaluations, leaves and decisions in those runs."""
    from experiments import bench_tree

    figures = _figures(name)
    assert figures["cpu_count"] == (1 if name.endswith("1") else 2)
    assert bench_tree.table(figures) == (RESULTS / f"{name}.md").read_text()
    for enclosure in bench_tree.ENCLOSURES:  # the capsule test and the cascade
        agreement = figures[enclosure]["agreement"]
        assert agreement["evaluations_equal"] and agreement["leaves_equal"] and agreement["decisions_equal"]
        assert agreement["guards_equal"] and agreement["clearance_max_abs_diff_m"] < 1e-12


@pytest.mark.parametrize("cpus", ["0", "999"])
def test_bench_tree_refuses_a_cpu_count_it_cannot_have(cpus):
    from experiments import bench_tree

    with pytest.raises(SystemExit) as exc:
        bench_tree.main(["--cpus", cpus])
    assert exc.value.code == 2
