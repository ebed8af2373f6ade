"""`cotpc bench train` and `cotpc bench act` run for every family (benchmarks are not tests: this only checks that
the commands work and report what they claim, at the smallest size)."""

import json

import pytest
import torch

from cotpc.cli.main import main as cotpc_main


@pytest.fixture(autouse=True)
def _restore_threads():
    """`--threads 1` sets torch's global thread count; later tests in this process must not inherit it (a test
    of another file learns differently at 1 thread)."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_bench_act_reports_amortised_and_worst_steps(capsys):
    cotpc_main(["bench", "act", "--policies", "bc", "cotpc", "dp", "--batch-sizes", "1", "--calls", "8",
                "--threads", "1", "--json"])
    out = json.loads(capsys.readouterr().out)
    assert out["cpu"]["model"] and isinstance(out["cpu"]["amx_bf16"], bool)  # the machine, with the numbers
    rows = {r["policy"]: r for r in out["rows"]}
    assert set(rows) == {"bc", "cotpc", "dp"}
    for r in rows.values():
        assert 0 < r["ms"] <= r["ms_max"] and r["ms_mean"] <= r["ms_max"]
    dp = rows["dp"]  # plans 8 actions at once: one slow step, seven nearly free ones
    assert dp["ms"] < dp["ms_mean"] < dp["ms_max"]


def test_bench_act_times_inference_variants_of_the_transformers_only(capsys):
    cotpc_main(["bench", "act", "--policies", "bc", "cotpc", "--batch-sizes", "2", "--calls", "3", "--rounds", "2",
                "--variants", "eager", "bf16", "--threads", "1", "--json"])
    rows = json.loads(capsys.readouterr().out)["rows"]
    assert sorted((r["policy"], r["variant"]) for r in rows) == [("bc", "eager"), ("cotpc", "bf16"), ("cotpc", "eager")]
    assert all(r["batch"] == 2 and 0 < r["ms"] <= r["ms_max"] for r in rows)


def test_bench_train_times_a_compiled_step(capsys):
    cotpc_main(["bench", "train", "--policies", "bc", "--settings", "maze", "--rounds", "1", "--iters", "1",
                "--warmup", "1", "--bf16", "False", "--threads", "1", "--json", "--compile", "off", "default"])
    rows = {r["policy"]: r for r in json.loads(capsys.readouterr().out)["rows"]}
    assert set(rows) == {"bc", "bc [default]"} and rows["bc [default]"]["compile"] == "default"
    assert rows["bc [default]"]["gflop_per_iter"] == rows["bc"]["gflop_per_iter"] > 0


def test_bench_train_runs_every_family(capsys):
    cotpc_main(["bench", "train", "--policies", "bc", "dp", "dd", "--settings", "maniskill", "--rounds", "1",
                "--iters", "1", "--warmup", "1", "--bf16", "False", "--threads", "1", "--json", "--batch-scales", "1", "2"])
    rows = {r["policy"]: r for r in json.loads(capsys.readouterr().out)["rows"]}
    assert set(rows) == {"bc", "dp", "dd", "bc x2", "dp x2", "dd x2"}
    assert all(r["ms_min"] > 0 and r["gflop_per_iter"] > 0 and not r["bf16"] and r["samples_per_s"] > 0
               for r in rows.values())
    with pytest.raises(SystemExit, match="--device"):
        cotpc_main(["bench", "train", "--policies", "bc", "--device", "tpu"])
    for name in ("bc", "dp", "dd"):  # the doubled batch is a doubled step: twice the samples and the FLOPs
        assert rows[f"{name} x2"]["batch_size"] == 2 * rows[name]["batch_size"]
        assert rows[f"{name} x2"]["gflop_per_iter"] == pytest.approx(2 * rows[name]["gflop_per_iter"], rel=0.05)



@pytest.mark.parametrize("args, says", [
    (["act", "--policies", "bet", "--calls", "0"], "cotpc bench act: --calls must be >= 1, got 0"),
    (["act", "--policies", "bet", "--batch-sizes", "1", "0"], "--batch-sizes must be >= 1, got 1 0"),
    (["train", "--policies", "bet", "--rounds", "0"], "cotpc bench train: --rounds must be >= 1, got 0"),
    (["train", "--policies", "bet", "--warmup", "-1"], "--warmup must be >= 0"),
])
def test_bench_flags_out_of_range_are_messages(args, says):
    with pytest.raises(SystemExit, match=says):
        cotpc_main(["bench", *args])
