"""Snakemake script of rule `report`: R/report.md from the model summary, stage times, metrics."""

import sys

from difftex.workflow.glue import write_report

with open(snakemake.log[0], "w") as log:  # noqa: F821 -- injected by Snakemake
    sys.stderr = sys.stdout = log
    write_report(snakemake.params.results, snakemake.output[0])  # noqa: F821
    print(f"wrote {snakemake.output[0]}")  # noqa: F821
