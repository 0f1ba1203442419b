# The bundled example: a small synthetic building, generated on first use (seconds to minutes).
# The per-stage config files (R/config/<stage>-<digest>.yaml), written when a run needs them.


rule synth_example:
    output:
        proxy=f"{wf.EXAMPLE_SCENE}/proxy.obj",
        manifest=f"{wf.EXAMPLE_SCENE}/synth.json",
    params:
        out=lambda wc, output: Path(output.proxy).parent,
    conda:
        "../envs/difftex.yaml"
    log:
        f"{config['results']}/logs/synth_example.log",
    benchmark:
        f"{config['results']}/benchmarks/synth_example.tsv"
    threads: 4
    resources:
        mem_mb=4000,
        runtime=30,
    shell:
        "difftex synth --preset tiny --out {params.out:q} > {log:q} 2>&1"


rule stage_config:
    input:
        # no inputs: the hook takes the run lock (and clears a crashed run's) in real runs
        lambda wc: RUN_GUARD(workflow),
    output:
        str(RES.stage_config("{stage}", "{digest}")),
    params:
        text=lambda wc: STAGE_TEXT[wc.stage],
    log:
        str(RES.log("stage_config", "{stage}-{digest}")),
    localrule: True
    conda:
        "../envs/difftex.yaml"
    # a shell job without Python (docs/workflow.md: a run: job starts a second Snakemake, a
    # Python start per file delays the first scene job); written to a temporary file and
    # renamed, so a crash never leaves half a config file
    shell:
        "(printf '%s' {params.text:q} > {output:q}.tmp && mv {output:q}.tmp {output:q}) > {log:q} 2>&1"


rule compute_config:
    output:
        str(RES.compute_config),
    params:
        text=STAGE_TEXT["compute"],
    log:
        str(RES.log("stage_config", "compute")),
    localrule: True
    conda:
        "../envs/difftex.yaml"
    shell:
        "(printf '%s' {params.text:q} > {output:q}.tmp && mv {output:q}.tmp {output:q}) > {log:q} 2>&1"
