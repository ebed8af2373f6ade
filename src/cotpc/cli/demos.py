"""``cotpc demos SUITE``: generate demonstrations in ManiSkill3's trajectory format, one subcommand per task suite
(:mod:`cotpc.studies.suites`; each suite's flags are its own)."""

from __future__ import annotations

import tyro

from cotpc.studies.suites import suite_of_config, suites


def main(argv: list[str], prog: str) -> None:
    cfg = tyro.extras.subcommand_cli_from_dict({name: s.demos for name, s in suites().items()}, args=argv, prog=prog)
    suite_of_config(cfg, "demos").make_demos(cfg)
