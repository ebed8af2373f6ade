"""``cotpc eval RUN --split {seen,val,unseen}``: batched rollouts with a 95% confidence interval, by the task
suite of the env id the run was trained on (:mod:`cotpc.studies.suites`)."""

from __future__ import annotations

import tyro

from cotpc.evaluation.request import EvalRequest
from cotpc.policies.policy import read_config
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
    run_eval(tyro.cli(EvalRequest, args=argv, prog=prog))
