"""``python -m cotpc VERB ...``: the same as the ``cotpc`` console script."""

from cotpc.cli.main import main

main()
