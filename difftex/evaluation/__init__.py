"""Evaluation: held-out views and texture metrics (evaluate, metrics), the baselines (baselines, mrf),
the peer programs (peers), and the HTML report of a run (report).

Imports nothing from the method's internals (the method package): the baselines and peers share only
photo sampling and composition with it."""
