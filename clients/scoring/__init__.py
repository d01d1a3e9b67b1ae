"""Scoring functions of the measurement campaigns (`rvs campaign` hooks: runs_from, score, report),
importable wherever a campaign's workers run."""
