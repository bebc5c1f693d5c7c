# stex over a dataset of captures in one run: the workflow (../Snakefile) once per scene file.
# Run: snakemake --snakefile workflow/dataset.smk --configfile my_dataset.yaml --cores 2
# where my_dataset.yaml is
#   scene_files: [captures/a.yaml, captures/b.yaml]   # one scene file each, as for ../Snakefile
#   common: {masks: {depth_far_m: 1.5}}              # optional: settings shared by every scene
# (an entry may be a list of files, merged in order: config/datasets/demo_and_fox.yaml)
# Each scene is exactly the run `snakemake --configfile <scene file>` would make in this
# directory (config/config.yaml, then common, then the scene file), in its own
# <results>/<scene>/; its rules are named <scene>_<rule> (e.g. fox_tracking).
# `scenes` (a key of the dataset file, or `--config scenes=[a,b]`) names the scenes a run makes
# and a report holds (default: all): with --keep-going, the scenes that did not fail finish, and
#   snakemake --snakefile workflow/dataset.smk --configfile my_dataset.yaml --config scenes=[a,b] --report report.html
# is their report (a report of a scene with missing results is refused, naming the scene).
import os
import re
import sys

from snakemake.utils import min_version

from stex.config import dataset_scene_configs

min_version("9.1")  # module names given by a variable


report: "report/dataset.rst"


include: "rules/scheduling.smk"


_WHERE = "the dataset config (scene_files, common, scenes)"
SCENES = dataset_scene_configs(config, where=_WHERE)  # the chosen ones (`scenes`), in dataset order
config["scenes"] = list(SCENES)  # the report's description names them
_PREFIXES = {}
for scene_name, scene_config in SCENES.items():
    # a rule name is a Python identifier: '-' and '.' of a scene name become '_'
    prefix = re.sub(r"\W", "_", scene_name if scene_name[0].isalpha() else f"scene_{scene_name}") + "_"
    if prefix in _PREFIXES:
        raise ValueError(
            f"scenes {_PREFIXES[prefix]!r} and {scene_name!r} give the same rule names ({prefix}*): rename one"
        )
    _PREFIXES[prefix] = scene_name

    module:
        name: scene_name
        snakefile:
            "../Snakefile"
        config:
            scene_config

    use rule * from scene_name as prefix*


# one writer per results folder: the run holds every scene's (rules/hooks.smk)
LOCKED_RESULTS = [f"{c['results']}/{name}" for name, c in SCENES.items()]


include: "rules/hooks.smk"


# A report of a scene with missing results: Snakemake's own refusal names one missing file of one
# scene; name every unfinished scene and the option that reports the others. Snakemake tells a
# workflow nothing about a report, so it is read from the command line (--report, or --reporter
# with its options; --report-after-run reports after the run, when the results exist).
if "--report-after-run" not in sys.argv and any(a.split("=")[0] in ("--report", "--reporter") for a in sys.argv):
    _missing = {
        name: [f for f in getattr(rules, f"{prefix}all").input if not os.path.exists(f)]
        for prefix, name in _PREFIXES.items()
    }
    _unfinished = [
        f"scene {name!r} is incomplete: {files[0]}"
        + (f" and {len(files) - 1} more of its results are" if len(files) > 1 else " is")
        + f" missing (its run failed or has not finished: see {SCENES[name]['results']}/{name}/logs)"
        for name, files in _missing.items()
        if files
    ]
    if _unfinished:
        _finished = [name for name, files in _missing.items() if not files]
        raise ValueError(
            "; ".join(_unfinished)
            + ". "
            + (
                f"Report the complete scenes with --config scenes=[{','.join(_finished)}]"
                if _finished
                else "None of these scenes is complete: finish their runs first"
            )
        )


rule all:
    default_target: True
    input:
        [getattr(rules, f"{prefix}all").input for prefix in _PREFIXES],
