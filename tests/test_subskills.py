"""Subskill discovery: exactness against brute force, batching, conventions, errors, CoT targets."""

import itertools

import numpy as np
import pytest

import cotpc.subskills.discovery as D
from cotpc.bench.segment import reference_dp
from cotpc.subskills import COSTS, cot_targets, discover, discover_batch, objective
from cotpc.subskills.evaluate import count_matches, score


def brute_force(a, beta, min_size, cost):
    """All segmentations of N actions (2^(N-1) of them): (best J, second best J, best ends)."""
    n = len(a)
    results = []
    for m in range(n):
        for cuts in itertools.combinations(range(n - 1), m):
            ends = list(cuts) + [n - 1]
            if np.diff([-1] + ends).min() >= min_size:
                results.append((objective(a, ends, beta, cost), ends))
    results.sort(key=lambda r: r[0])
    second = results[1][0] if len(results) > 1 else np.inf
    return results[0][0], second, results[0][1]


def random_actions(rng, n, p):
    """Gaussian actions with the awkward cases mixed in: zero actions, duplicates, exactly cancelling pairs."""
    a = rng.normal(size=(n, p))
    if rng.random() < 0.3:
        a[rng.random(n) < 0.3] = 0.0
    if rng.random() < 0.3:
        a[rng.integers(n)] = a[0]
    if rng.random() < 0.3 and n > 1:
        k = rng.integers(1, n)
        a[k] = -a[k - 1]
    if rng.random() < 0.2:
        a = np.round(a)  # many exact duplicates and zeros
    return a


def check_valid(ends, n, min_size):
    assert ends.dtype == np.int64 and ends.ndim == 1
    assert ends[-1] == n - 1 and np.all(np.diff(ends) > 0)
    assert np.diff(np.concatenate([[-1], ends])).min() >= min_size


@pytest.mark.parametrize("cost", COSTS)
def test_matches_brute_force(cost):
    rng = np.random.default_rng(0)
    cases = 0
    while cases < 300:
        n, p, min_size = int(rng.integers(1, 11)), int(rng.integers(1, 4)), int(rng.integers(1, 4))
        if n < min_size:
            continue
        a = random_actions(rng, n, p)
        beta = float(rng.choice([0.0, 0.01, 0.05, 0.2, 1.0]))
        ends = discover(a, beta, min_size, cost)
        check_valid(ends, n, min_size)
        best, second, best_ends = brute_force(a, beta, min_size, cost)
        assert objective(a, ends, beta, cost) == pytest.approx(best, abs=1e-9), (a, beta, min_size, ends, best_ends)
        if second - best > 1e-7:  # unique optimum: the very same segmentation
            assert ends.tolist() == best_ends
        cases += 1


@pytest.mark.parametrize("cost", COSTS)
def test_matches_direct_sum_reference_on_long_inputs(cost):
    # N = 80: beyond brute force; the reference DP sums every segment directly instead of using prefix sums.
    rng = np.random.default_rng(1)
    for k in range(6):
        dirs = rng.normal(size=(4, 5))
        a = dirs[np.repeat(np.arange(4), 20)] + [0.05, 0.3, 1.0][k % 3] * rng.normal(size=(80, 5))
        a[rng.random(80) < 0.05] = 0.0
        beta = 0.03 if cost == "mean-cosine" else 1.0
        ours, ref = discover(a, beta, 2, cost), reference_dp(a, beta, 2, cost)
        assert objective(a, ours, beta, cost) == pytest.approx(objective(a, ref, beta, cost), abs=1e-9)


def test_batch_equals_single_with_many_groups_and_blocks(monkeypatch):
    # a tiny memory budget forces many groups (run by the worker threads) and many column blocks per group
    monkeypatch.setattr(D, "_BLOCK_ELEMS", 4000)
    rng = np.random.default_rng(2)
    arrays = [random_actions(rng, int(rng.integers(1, 70)), 3) for _ in range(40)]
    for cost in COSTS:
        batch = discover_batch(arrays, 0.05, 1, cost)
        assert len(batch) == len(arrays)
        for a, e in zip(arrays, batch):
            np.testing.assert_array_equal(e, discover(a, 0.05, 1, cost))
            check_valid(e, len(a), 1)
    assert discover_batch([], 0.1) == []


def test_not_worse_than_random_segmentations():
    rng = np.random.default_rng(3)
    for _ in range(10):
        n = 60
        a = rng.normal(size=(n, 4)) + np.repeat(rng.normal(size=(3, 4)) * 2, 20, axis=0)
        for cost, beta in (("mean-cosine", 0.05), ("sum-cosine", 1.0)):
            j = objective(a, discover(a, beta, 1, cost), beta, cost)
            for _ in range(20):
                m = int(rng.integers(0, 10))
                ends = sorted(set(rng.choice(n - 1, size=m, replace=False).tolist())) + [n - 1]
                assert j <= objective(a, ends, beta, cost) + 1e-12


def test_recovers_clean_piecewise_constant_directions():
    dirs = np.array([[1.0, 0.0], [0.0, 1.0], [-1.0, 0.2]])
    a = np.repeat(dirs, [5, 7, 4], axis=0) * np.linspace(1, 3, 16)[:, None]  # magnitudes vary, directions don't
    for cost in COSTS:
        assert discover(a, 0.05, 1, cost).tolist() == [4, 11, 15]


@pytest.mark.parametrize("cost", COSTS)
def test_invariant_to_global_positive_scaling(cost):
    rng = np.random.default_rng(4)
    for _ in range(8):
        a = random_actions(rng, 30, 3)
        ends = discover(a, 0.05, 1, cost)
        for c in (1e-6, 0.37, 12.0, 1e5):
            np.testing.assert_array_equal(discover(a * c, 0.05, 1, cost), ends)
            assert objective(a * c, ends, 0.05, cost) == pytest.approx(objective(a, ends, 0.05, cost), abs=1e-12)


def test_per_action_scaling_is_not_an_invariance():
    # The cost compares each action with the segment *mean*, and rescaling one action moves the mean: here
    # C([e1, e2]) = 1 - 1/sqrt(2) = 0.29 but C([e1, 10 e2]) = 0.45, so with beta = 0.35 one keeps one segment and
    # the other splits. Only a common factor for all actions leaves the result unchanged (test above).
    a = np.array([[1.0, 0.0], [0.0, 1.0]])
    assert objective(a, [1], 0.0) == pytest.approx(1 - 1 / np.sqrt(2))
    assert discover(a, 0.35).tolist() == [1]
    assert discover(a * [[1.0], [10.0]], 0.35).tolist() == [0, 1]


def test_zero_action_convention():
    z = np.zeros((6, 3))
    for cost in COSTS:
        assert discover(z, 0.1, 1, cost).tolist() == [5]  # all-zero segment costs 0, so one segment
        assert objective(z, [5], 0.1, cost) == pytest.approx(0.1)
        assert objective(z, [1, 5], 0.1, cost) == pytest.approx(0.2)
    x = np.array([3.0, 4.0, 0.0])
    # d(0, x) = 1 and d(x, x/2) = 0: mean 0.5
    assert objective(np.array([x, 0 * x]), [1], 0.0) == pytest.approx(0.5)
    # actions cancel (zero mean): d(x, 0) = 1 for non-zero x, d(0, 0) = 0
    assert objective(np.array([x, -x]), [1], 0.0) == pytest.approx(1.0)
    assert objective(np.array([x, 0 * x, -x]), [2], 0.0) == pytest.approx(2 / 3)
    assert objective(np.array([x, 0 * x, -x]), [2], 0.0, "sum-cosine") == pytest.approx(2.0)
    # "zero" is relative to the largest action of the trajectory
    tiny = np.array([[1.0, 0.0], [0.0, 1e-13], [1.0, 0.0]])
    assert objective(tiny, [2], 0.0) == pytest.approx(1 / 3)
    # the DP agrees and produces no NaN on inputs full of zeros and cancellations
    rng = np.random.default_rng(5)
    for _ in range(20):
        a = np.round(rng.normal(size=(12, 2)))
        a[rng.random(12) < 0.4] = 0.0
        e = discover(a, 0.02)
        assert np.isfinite(objective(a, e, 0.02))
        assert objective(a, e, 0.02) == pytest.approx(objective(a, reference_dp(a, 0.02), 0.02), abs=1e-9)


def test_bad_input_raises():
    ok = np.ones((5, 2))
    bad = [
        (np.ones(5), 0.1, 1, "2-D"),
        (np.ones((2, 3, 4)), 0.1, 1, "2-D"),
        (np.ones((0, 2)), 0.1, 1, "empty"),
        (np.ones((5, 0)), 0.1, 1, "empty"),
        (np.array([[1.0, np.nan]]), 0.1, 1, "NaN"),
        (np.array([[1.0, np.inf]]), 0.1, 1, "NaN/inf"),
        (np.array([["a", "b"]]), 0.1, 1, "real numbers"),
        (ok, -0.1, 1, "beta"),
        (ok, float("nan"), 1, "beta"),
        (ok, 0.1, 0, "min_size"),
        (ok, 0.1, 1.5, "min_size"),
        (ok, 0.1, 6, "min_size"),
    ]
    for a, beta, min_size, msg in bad:
        with pytest.raises(ValueError, match=msg):
            discover(a, beta, min_size)
    with pytest.raises(ValueError, match="cost"):
        discover(ok, 0.1, 1, "l2")
    with pytest.raises(ValueError, match="dimension"):
        discover_batch([ok, np.ones((5, 3))], 0.1)
    for ends in ([1, 3], [2, 2, 4], [-1, 4], [4.5], [], [[4]]):
        with pytest.raises(ValueError):
            objective(ok, ends, 0.1)


def test_cot_targets_hand_worked():
    obs = np.arange(12, dtype=np.float64).reshape(6, 2)  # s(0..5), N = 5 actions
    nxt, last = cot_targets(obs, np.array([1, 4]))  # segments a0..a1 | a2..a4; key states s(2), s(5)
    assert nxt.dtype == np.float32 and last.dtype == np.float32
    np.testing.assert_array_equal(nxt, obs[[2, 2, 5, 5, 5]])
    np.testing.assert_array_equal(last, obs[[5] * 5])
    nxt, _ = cot_targets(obs, np.arange(5))  # one action per segment: the next key state is s(t + 1)
    np.testing.assert_array_equal(nxt, obs[1:])
    nxt, _ = cot_targets(obs, [4])  # one segment: next = last = final state
    np.testing.assert_array_equal(nxt, obs[[5] * 5])
    with pytest.raises(ValueError):
        cot_targets(obs, [1, 3])  # last end must be N - 1 = 4
    with pytest.raises(ValueError):
        cot_targets(obs[:, 0], [4])


def test_key_step_matching():
    assert count_matches(np.array([3, 10]), np.array([4, 11]), 2) == 2
    assert count_matches(np.array([3, 4]), np.array([4]), 2) == 1  # one-to-one
    assert count_matches(np.array([1, 5]), np.array([3, 7]), 2) == 2  # greedy must not pair 5 with 3
    assert count_matches(np.array([1]), np.array([4]), 2) == 0
    s = score([np.array([2, 9]), np.array([9])], [np.array([3]), np.array([5])], tol=2)
    assert (s["matched"], s["predicted"], s["true"]) == (1, 1, 2)
    assert s["precision"] == 1.0 and s["recall"] == 0.5
    assert (s["subskills_min"], s["subskills_max"], s["length_max"]) == (1, 2, 10)
