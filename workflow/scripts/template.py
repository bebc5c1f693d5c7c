"""Thin adapter: rule template -> stex.stages.template.write_template."""
from stex.logs import setup_logging
from stex.stages.template import write_template

setup_logging(snakemake.log[0])
first = list(snakemake.input.first) or [None, None]  # template.from_depth / align / from_scan: block 0
scan = list(snakemake.input.scan) or [None]  # template.from_scan: the fused scan
write_template(snakemake.input.scene, snakemake.params.template, snakemake.output[0], *first, scan[0],
               masks_params=snakemake.params.masks)
