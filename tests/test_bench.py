"""`lobula bench` times what it is asked to: a skipped stage is not run."""
from experiments import bench


def test_skipped_stages_are_not_run(monkeypatch, capsys):
    def must_not_run(*a, **k):
        raise AssertionError("a skipped stage ran")

    for name in ("bench_render", "bench_emd", "bench_tv_depth"):
        monkeypatch.setattr(bench, name, must_not_run)
    monkeypatch.setattr("experiments.ephys.bench_tuning_sweep", must_not_run)
    rows = bench.run_bench(frames=12, scales=(0.25,), presets=("ultrafast",), skip=tuple(bench.SKIPPABLE))
    assert len(rows) == 1 and rows[0]["size"] == "160x120" and rows[0]["end_to_end"] > 0
    assert "ephys tuning sweep" not in capsys.readouterr().out


def test_an_unknown_stage_is_refused(capsys):
    from experiments.cli import main

    assert main(["bench", "--skip", "flow"]) == 2
    assert "invalid choice: 'flow'" in capsys.readouterr().err


def test_too_few_frames_for_a_flow_pair_name_the_option(monkeypatch, capsys):
    from experiments.cli import main

    def must_not_run(*a, **k):
        raise AssertionError("the benchmark ran")

    monkeypatch.setattr(bench, "run_bench", must_not_run)
    assert main(["bench", "--frames", "6"]) != 0
    err = capsys.readouterr().err
    assert "--frames 6" in err and "at least 7 frames" in err and len(err.strip().splitlines()) == 1
