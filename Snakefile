# stex workflow: spatiotemporal texture reconstruction from one RGB-D camera.
# Run: snakemake --cores 2   (scene: config/config.yaml; others: --configfile config/scenes/<name>.yaml)
from snakemake.utils import min_version, validate

from stex.config import SCHEMA_PATH

min_version("9.0")


configfile: "config/config.yaml"


# the schema ships inside the package: library functions read their defaults from it too
validate(config, str(SCHEMA_PATH))


report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/ingest.smk"
include: "workflow/rules/masks.smk"
include: "workflow/rules/template.smk"
include: "workflow/rules/tracking.smk"
include: "workflow/rules/poses.smk"
include: "workflow/rules/projection.smk"
include: "workflow/rules/texcoords.smk"
include: "workflow/rules/baseline.smk"
include: "workflow/rules/observations.smk"
include: "workflow/rules/tables.smk"
include: "workflow/rules/labeling.smk"
include: "workflow/rules/volume.smk"
include: "workflow/rules/correction.smk"
include: "workflow/rules/evaluate.smk"


rule all:
    input:
        all_outputs(),
    default_target: True
