# stex over a dataset of captures in one run: the workflow (../Snakefile) once per scene file.
# Run: snakemake --snakefile workflow/dataset.smk --configfile my_dataset.yaml --cores 2
# where my_dataset.yaml is
#   scene_files: [captures/a.yaml, captures/b.yaml]   # one scene file each, as for ../Snakefile
#   common: {masks: {depth_far_m: 1.5}}              # optional: settings shared by every scene
# (an entry may be a list of files, merged in order: config/datasets/demo_and_fox.yaml)
# Each scene is exactly the run `snakemake --configfile <scene file>` would make in this
# directory (config/config.yaml, then common, then the scene file), in its own
# <results>/<scene>/; its rules are named <scene>_<rule> (e.g. fox_tracking).
import re

from snakemake.utils import min_version

from stex.config import dataset_scene_configs

min_version("9.1")  # module names given by a variable


report: "report/dataset.rst"


SCENES = dataset_scene_configs(config, where="the dataset config (scene_files, common)")
_PREFIXES = {}
for scene_name, scene_config in SCENES.items():
    # a rule name is a Python identifier: '-' and '.' of a scene name become '_'
    prefix = re.sub(r"\W", "_", scene_name if scene_name[0].isalpha() else f"scene_{scene_name}") + "_"
    if prefix in _PREFIXES:
        raise ValueError(f"scenes {_PREFIXES[prefix]!r} and {scene_name!r} give the same rule names ({prefix}*): rename one")
    _PREFIXES[prefix] = scene_name

    module:
        name: scene_name
        snakefile: "../Snakefile"
        config: scene_config

    use rule * from scene_name as prefix*


rule all:
    input:
        [getattr(rules, f"{prefix}all").input for prefix in _PREFIXES],
    default_target: True
