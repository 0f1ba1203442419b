# difftex: texturing planar building proxies from registered photos (DiffTex, ACM TOG 2025).
#
#   snakemake --cores all                                   # the bundled synthetic example
#   snakemake --cores all --config scene=path/to/scene      # any scene (images/, sparse/0/, proxy.obj)
#   snakemake --cores all --config scene=... preset=fast 'optimize={lr: 0.01}'
#
# Results: <results>/<scene name>/ in the working directory (see docs/workflow.md).
# A failed run ends with the failed jobs' one-line errors and their logs; the same command
# resumes after a crash or a kill (docs/failures.md).

from snakemake.utils import min_version

min_version("9.0")


include: "workflow/rules/common.smk"
include: "workflow/rules/scene.smk"
include: "workflow/rules/filter.smk"
include: "workflow/rules/dense.smk"
include: "workflow/rules/visibility.smk"
include: "workflow/rules/heights.smk"
include: "workflow/rules/texture.smk"
include: "workflow/rules/assemble.smk"
include: "workflow/rules/evaluate.smk"


localrules:
    all,
    report,
    compose,
    finish,


rule all:
    input:
        # the run guard first: it takes the run lock in real runs, then runs again the finished
        # jobs that lost a polygon's file (and adds no input)
        get_run_start,
        # the per-polygon stages' config files, wanted from the start: asked for only after the
        # visibility checkpoint, they would be a round of jobs between it and the texture jobs
        PER_POLYGON_CFG,
        # every visibility tile's and per-polygon job's list (the latter after the checkpoint): a
        # finished job that lost a file runs again
        TILE_ROWS,
        get_polygon_job_files,
        str(RES.model_summary),
        str(RES.report_md),
        str(RES.report_html),
        # COLMAP PatchMatch stereo's workspace, with dense.stereo: true only (workflow/rules/dense.smk)
        DENSE_STEREO,
    default_target: True


onsuccess:
    RUN_GUARD.finished = True
    runlog.print_warnings(R)
    wf.print_summary(R)


onerror:
    RUN_GUARD.finished = True
    runlog.report_failure(workflow, R, RUN_GUARD.started, RUN_GUARD.interrupted)
