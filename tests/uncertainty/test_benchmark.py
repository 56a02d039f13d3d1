from uncertainty.benchmark import run_score_bench


def test_score_bench_reports_both_paths_from_one_run():
    out = run_score_bench(members=2, image_size=16, seconds=0.3, batch=4, threads=1, rounds=1)
    assert out["fused_fps"] > 0 and out["loop_fps"] > 0 and out["vmap_fps"] > 0
    assert out["speedup"] == out["fused_fps"] / out["loop_fps"]
    assert out["max_abs_diff"] < 1e-5 and out["config"]["members"] == 2


def test_score_bench_counts_the_same_arithmetic_for_both_paths():
    out = run_score_bench(members=2, image_size=16, seconds=0.3, batch=4, threads=1, rounds=1,
                          include_vmap=False)
    # Same work, so GFLOP/s scale with frames/s; the ceiling is measured in the same run.
    assert out["gflop_per_frame"] > 0 and out["ceiling_gflops"] > 0
    assert abs(out["fused_gflops"] / out["loop_gflops"] - out["speedup"]) < 1e-6 * out["speedup"]
    assert out["loop_share_of_ceiling"] == out["loop_gflops"] / out["ceiling_gflops"]
