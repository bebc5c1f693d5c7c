# stex workflow: spatiotemporal texture reconstruction from one RGB-D camera.
# Run: snakemake --cores 2   (scene: config/config.yaml; others: --configfile config/scenes/<name>.yaml)
from snakemake.utils import min_version

from stex.config import validate_config

min_version("9.0")


configfile: "config/config.yaml"


# the schema ships inside the package: library functions read their defaults from it too.
# stex's validator (the same schema and defaults, in the same key order as snakemake's) names
# the key and what is allowed in one line, instead of printing the schema and the config
_validated = validate_config(config)
config.clear()
config.update(_validated)


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/scheduling.smk"


LOCKED_RESULTS = [RESULTS]  # one writer per results folder (workflow/rules/hooks.smk)


include: "workflow/rules/hooks.smk"
include: "workflow/rules/ingest.smk"
include: "workflow/rules/masks.smk"
include: "workflow/rules/template.smk"
include: "workflow/rules/tracking.smk"
include: "workflow/rules/poses.smk"
include: "workflow/rules/projection.smk"
include: "workflow/rules/texcoords.smk"
include: "workflow/rules/global_texture.smk"
include: "workflow/rules/observations.smk"
include: "workflow/rules/data_term.smk"
include: "workflow/rules/labeling.smk"
include: "workflow/rules/volume.smk"
include: "workflow/rules/correction.smk"
include: "workflow/rules/references.smk"
include: "workflow/rules/evaluate.smk"
include: "workflow/rules/view.smk"


rule all:
    default_target: True
    input:
        all_outputs(),
