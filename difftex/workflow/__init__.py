"""Workflow glue for the Snakemake rules (Snakefile, workflow/rules/*.smk): config merging and
per-stage config files, scene inputs, resource estimates and the end-of-run summary (glue); the
one-run-per-results-folder lock (runguard) and the run log (runlog)."""
