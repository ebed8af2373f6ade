"""``cotpc reproduce SUITE``: a whole study in one command, one subcommand per task suite (cotpc/studies/)."""

from __future__ import annotations

import tyro

from cotpc.studies.suites import suite_of_config, suites


def main(argv: list[str], prog: str) -> None:
    cfg = tyro.extras.subcommand_cli_from_dict({name: s.reproduce for name, s in suites().items()}, args=argv,
                                               prog=prog)
    suite_of_config(cfg, "reproduce").run_study(cfg)
