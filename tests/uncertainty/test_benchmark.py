from uncertainty.benchmark import run_score_bench


def test_score_bench_reports_both_paths_from_one_run():
    out = run_score_bench(members=2, image_size=16, seconds=0.3, batch=4, threads=1, rounds=1)
    assert out["fused_fps"] > 0 and out["loop_fps"] > 0 and out["vmap_fps"] > 0
    assert out["speedup"] == out["fused_fps"] / out["loop_fps"]
    assert out["max_abs_diff"] < 1e-5 and out["config"]["members"] == 2
