"""``cotpc eval RUN --split {seen,val,unseen}``: batched rollouts with a 95% confidence interval, by the task
suite of the env id the run was trained on (:mod:`cotpc.studies.suites`)."""

from __future__ import annotations

import sys

import tyro

from cotpc.data.trajectories import TrajectoryFormatError

from cotpc.evaluation.request import EvalRequest
from cotpc.policies.policy import CheckpointError, read_config
from cotpc.studies.suites import suite_for_env, suites


def run_eval(req: EvalRequest) -> dict:
    info = read_config(req.run)
    env_id = info.get("dataset", {}).get("env_id")
    suite = suite_for_env(env_id)
    if suite is None:
        raise SystemExit(f"cotpc eval: {req.run} was trained on {env_id!r}, which no task suite evaluates "
                         f"(suites: {', '.join(suites())})")
    return suite.evaluate(req, info, env_id)


def main(argv: list[str], prog: str) -> None:
    req = tyro.cli(EvalRequest, args=argv, prog=prog)
    try:
        run_eval(req)
    except (CheckpointError, TrajectoryFormatError, FileNotFoundError) as e:  # a bad run or demo file: no traceback
        print(f"{prog}: error: {e}", file=sys.stderr)
        raise SystemExit(2)
