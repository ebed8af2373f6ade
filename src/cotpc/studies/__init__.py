"""The studies: each environment's comparison of policies and seeds (``cotpc reproduce``) as a declaration over
the shared machinery of :mod:`cotpc.studies.runs` (train a grid, reuse what is on disk, evaluate, report)."""
