"""Configuration: load YAML, validate against the schema (stex/schema.yaml) and fill in the defaults.

The workflow (the Snakefile, ``workflow/dataset.smk``), library users, the CLI and tests all
validate with :func:`validate_config`: one schema, one set of defaults, errors in one line.
"""

from __future__ import annotations

import copy
import math
from pathlib import Path

import jsonschema
import yaml

# inside the package, so that an installed wheel has the defaults its stage functions read
SCHEMA_PATH = Path(__file__).resolve().parent / "schema.yaml"


def _with_defaults(validator_class):
    validate_properties = validator_class.VALIDATORS["properties"]

    def set_defaults(validator, properties, instance, schema):
        if isinstance(instance, dict):
            for name, sub in properties.items():
                if "default" in sub and name not in instance:
                    instance[name] = copy.deepcopy(sub["default"])
        yield from validate_properties(validator, properties, instance, schema)

    return jsonschema.validators.extend(validator_class, {"properties": set_defaults})


def load_schema(path: str | Path = SCHEMA_PATH) -> dict:
    # libyaml's loader when PyYAML has it: every snakemake start (every cluster job) reads the schema
    return yaml.load(Path(path).read_text(), Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


def validate_config(config: dict, schema: dict | None = None) -> dict:
    """Return a validated copy of ``config`` with every default filled in.

    Raises ValueError naming the offending key path on invalid input.
    """
    schema = schema or load_schema()
    cfg = copy.deepcopy(config or {})
    validator = _with_defaults(jsonschema.Draft202012Validator)(schema)
    errors = sorted(validator.iter_errors(cfg), key=lambda e: list(e.path))
    if errors:
        raise ValueError(_error_message(errors[0]))
    cfg = _numbers(cfg, schema)
    check_relations(cfg)
    return schema_order(cfg, schema)


def _numbers(instance, schema: dict, where: str = ""):
    """``instance`` (valid against ``schema``) with whole floats of integer settings made ints
    and non-finite numbers refused (ValueError naming the key). JSON Schema counts 8.0 as an
    integer, but numpy and range() do not: ``frame_block: 8.0`` passed and failed later in a
    raw TypeError; ``.nan`` passes every minimum (a comparison with NaN is false)."""
    if isinstance(instance, dict):
        props = schema.get("properties") or {}
        extra = schema.get("additionalProperties")
        extra = extra if isinstance(extra, dict) else {}
        return {k: _numbers(v, props.get(k, extra), f"{where}/{k}" if where else str(k))
                for k, v in instance.items()}
    if isinstance(instance, list):
        items = schema.get("items") if isinstance(schema.get("items"), dict) else {}
        return [_numbers(v, items, f"{where}/{i}") for i, v in enumerate(instance)]
    if isinstance(instance, float) and not isinstance(instance, bool):
        if not math.isfinite(instance):
            raise ValueError(f"config error at {where or '<top level>'}: {instance} is not a finite number")
        types = schema.get("type")
        types = types if isinstance(types, list) else [types]
        if "integer" in types and "number" not in types and instance.is_integer():
            return int(instance)
    return instance


def schema_order(instance, schema: dict):
    """``instance`` with the keys of every mapping the schema describes in the schema's order
    (names the schema does not list, e.g. other_methods' method names, after them as given).

    Snakemake compares a job's parameters by their ``repr``, keys in order, and the defaults are
    filled in after the keys a config file gives: without this, writing a default value out
    (``masks: {depth_far_m: 1.6}``) re-ran the stage and everything after it.
    """
    if isinstance(instance, dict):
        props = schema.get("properties") or {}
        extra = schema.get("additionalProperties")
        extra = extra if isinstance(extra, dict) else {}
        names = [k for k in props if k in instance] + [k for k in instance if k not in props]
        return {k: schema_order(instance[k], props.get(k, extra)) for k in names}
    if isinstance(instance, list) and isinstance(schema.get("items"), dict):
        return [schema_order(v, schema["items"]) for v in instance]
    return instance


def _error_message(e: jsonschema.ValidationError) -> str:
    """One line: where, what is wrong, and what is allowed (or why YAML read it so)."""
    where = "/".join(str(p) for p in e.absolute_path) or "<top level>"
    msg = f"config error at {where}: {e.message}"
    if e.validator in ("oneOf", "anyOf") and e.context:
        # "is not valid under any of the given schemas" says nothing of why: the error of the
        # alternative of the value's own type does (e.g. the misspelt key of a {slices, uv_mesh})
        deeper = [c for c in e.context if c.validator != "type"]
        if deeper:
            return _error_message(min(deeper, key=lambda c: len(c.absolute_path)))
        wanted = [c.validator_value for c in e.context]
        return f"config error at {where}: {e.instance!r} is none of the allowed kinds ({wanted})"
    if e.validator == "additionalProperties" and isinstance(e.schema.get("properties"), dict):
        msg += f"; allowed: {', '.join(sorted(e.schema['properties']))}"
    elif e.validator == "enum" and isinstance(e.instance, bool):
        msg += " (YAML reads an unquoted off / on / yes / no as false / true: quote it, e.g. 'off')"
    elif e.validator == "type" and isinstance(e.instance, str):
        try:
            float(e.instance)
        except ValueError:
            pass
        else:
            wanted = e.validator_value if isinstance(e.validator_value, list) else [e.validator_value]
            if "number" in wanted:  # PyYAML reads 1e-4 (no decimal point) as text
                msg += f" (YAML reads {e.instance} as text: write it with a decimal point, e.g. 1.0e-4)"
            else:
                msg += f" (written as text: give the number without quotes, e.g. {e.instance.strip(chr(34) + chr(39))})"
    return msg


#: evaluation settings read only by the merge into figures (stex.stages.evaluation.write_evaluation):
#: left out of the per-block scoring jobs' parameters and records, so that changing them re-draws
#: the figures without re-scoring every frame
FIGURE_SETTINGS = ("figure_frame", "dynamism_regions")


def scoring_settings(evaluation: dict) -> dict:
    """The evaluation section without :data:`FIGURE_SETTINGS`: what scoring a frame depends on."""
    return {k: v for k, v in evaluation.items() if k not in FIGURE_SETTINGS}


#: method names of the evaluation (stex.reporting.METHODS, the input images and the truth): not
#: for other methods (tests/test_config.py keeps the two in step)
RESERVED_METHOD_NAMES = ("ours", "ours_uncorrected", "global", "projection", "input", "truth")


def check_relations(config: dict) -> None:
    """Rules between settings that the JSON schema cannot state; ValueError naming the keys.

    Checked with the config, so that a run stops before its first job rather than in the stage
    that needs the rule, after the stages before it."""
    masks = config.get("masks") or {}
    near, far = masks.get("depth_near_m"), masks.get("depth_far_m")
    if near is not None and far is not None and near >= far:
        raise ValueError(f"config error at masks: depth_near_m ({near:g} m) must be below depth_far_m ({far:g} m)")
    template = config.get("template") or {}
    W, solve = template.get("atlas_size"), (config.get("correction") or {}).get("solve_size")
    if W is not None and solve is not None and W % max(1, W // solve):
        raise ValueError(f"config error at correction/solve_size: the atlas side template.atlas_size {W} is "
                         f"not divisible by the factor {W // solve} = {W} // {solve}; give a solve_size whose "
                         f"factor divides it, or {W} (full resolution)")
    gutter = template.get("gutter_px")
    if W is not None and gutter is not None and W - 2 * gutter < 8:
        raise ValueError(f"config error at template/gutter_px: {gutter} texels on either side leave "
                         f"{W - 2 * gutter} of the atlas side template.atlas_size {W} for the charts; "
                         f"give at most {(W - 8) // 2} (default 4)")
    # Decimated meshes end at target_faces, smaller ones are split up to min_faces: below it, a mesh
    # just over the target would end with fewer faces than one just under it.
    target, least = template.get("target_faces"), template.get("min_faces")
    if template.get("decimate", True) and target is not None and least is not None and target < least:
        raise ValueError(f"config error at template/target_faces: decimation (template.decimate) takes larger "
                         f"meshes down to target_faces {target}, below template.min_faces {least}, up to which "
                         f"smaller meshes are split, so a mesh just over the target would end with fewer faces "
                         f"than one just under it; give target_faces >= min_faces (e.g. min_faces: {target}, "
                         f"or 0: no splitting)")
    steps = (config.get("sampling_table") or {}).get("steps")
    if steps and 1 not in steps:
        raise ValueError(f"config error at sampling_table/steps: {steps} needs 1 (every frame a key frame: "
                         f"the reference the error ratios are taken against)")
    if template.get("from_depth") and template.get("uv") == "mesh":
        raise ValueError("config error at template: uv: mesh keeps the source template's own UV layout, but "
                         "from_depth builds a mesh without one; use uv: xatlas")
    if template.get("from_depth") and (config.get("tracking") or {}).get("mode") == "given":
        raise ValueError("config error at tracking/mode: given meshes refer to the source's template, but "
                         "template.from_depth builds another one; use tracking.mode: track")
    others = ((config.get("evaluation") or {}).get("other_methods") or {})
    reserved = sorted(set(others) & set(RESERVED_METHOD_NAMES))
    if reserved:
        raise ValueError(f"config error at evaluation/other_methods: {reserved} name methods the evaluation "
                         f"scores itself; not {', '.join(RESERVED_METHOD_NAMES)}")


def deep_update(base: dict, override: dict) -> dict:
    """Recursively merge ``override`` into a copy of ``base`` (like snakemake's --configfile)."""
    out = copy.deepcopy(base)
    for k, v in (override or {}).items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_update(out[k], v)
        else:
            out[k] = copy.deepcopy(v)
    return out


def read_settings(path: str | Path, where: str = "", what: str = "config file") -> dict:
    """The settings of one YAML config file (an empty file gives {}); FileNotFoundError or
    ValueError naming it (``where: what path ...``) when it is missing or not a mapping."""
    prefix = f"{where}: " if where else ""
    if not Path(path).is_file():
        rel = "" if Path(path).is_absolute() else f" (relative paths are read from the working directory {Path.cwd()})"
        raise FileNotFoundError(f"{prefix}{what} {path} not found{rel}")
    try:
        settings = yaml.safe_load(Path(path).read_text()) or {}
    except yaml.YAMLError as e:
        mark = getattr(e, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        raise ValueError(f"{prefix}{what} {path} is not valid YAML{at}: "
                         f"{getattr(e, 'problem', None) or e}") from None
    if not isinstance(settings, dict):
        raise ValueError(f"{prefix}{what} {path} is not a mapping of settings")
    return settings


def load_config(*paths: str | Path, overrides: dict | None = None) -> dict:
    """Merge YAML files left to right (then ``overrides``), validate and fill defaults."""
    cfg: dict = {}
    for p in paths:
        cfg = deep_update(cfg, read_settings(p))
    return validate_config(deep_update(cfg, overrides or {}))


_SCHEMA_CACHE: dict | None = None


def section_params(section: str, params: dict | None = None) -> dict:
    """One config section completed with the schema's defaults and validated.

    The schema is the single source of defaults: library functions called without the workflow
    (tests, benchmarks, the CLI) get exactly the values Snakemake would fill in. Unknown keys
    and out-of-range values raise ValueError naming the key.
    """
    global _SCHEMA_CACHE
    if _SCHEMA_CACHE is None:
        _SCHEMA_CACHE = load_schema()
    sub = _SCHEMA_CACHE["properties"].get(section)
    if sub is None:
        raise ValueError(f"the schema ({SCHEMA_PATH.name}) has no section {section!r}")
    schema = {"type": "object", "properties": {section: sub}}
    cfg = {section: copy.deepcopy(params) if params else {}}
    validator = _with_defaults(jsonschema.Draft202012Validator)(schema)
    errors = sorted(validator.iter_errors(cfg), key=lambda e: list(e.path))
    if errors:
        raise ValueError(_error_message(errors[0]))
    cfg = _numbers(cfg, schema)
    check_relations(cfg)
    return schema_order(cfg[section], sub)


DATASET_KEYS = {"scene_files", "common", "scenes"}


def dataset_scene_configs(dataset: dict, base: str | Path | None = "config/config.yaml",
                          where: str = "dataset") -> dict[str, dict]:
    """The validated config of every scene of a dataset (workflow/dataset.smk), by scene name.

    Each scene is ``base`` (when that file exists: the workflow's default config, as Snakemake's
    ``configfile:`` reads it from the working directory), then ``dataset['common']`` (settings
    shared by the captures, e.g. ``results`` or the rig's ``masks`` range), then its scene file:
    what ``snakemake --configfile <scene file>`` runs, plus the shared settings.

    Args:
        dataset: ``{"scene_files": [path, ...], "common": {...}, "scenes": [name, ...]}``
            (``common`` and ``scenes`` optional); an entry of ``scene_files`` may be a list of
            paths, merged left to right as several ``--configfile`` files are (e.g.
            ``[config/scenes/fox.yaml, config/scenes/fox_heldout.yaml]``). ``scenes`` (a name or
            a list of names; absent or None: all) picks the scenes returned, in the dataset's
            order; every scene file is read and checked either way.
        base: the default config file, or None.
        where: how to name the dataset in errors (e.g. its file).
    Raises:
        ValueError naming the dataset and the scene file: unknown keys, no scene files, a scene
        file that is not a mapping or whose config is invalid, two scene files naming one scene,
        ``scenes`` naming none or a scene the dataset does not have.
        FileNotFoundError naming a missing scene file.
    """
    unknown = sorted(set(dataset or {}) - DATASET_KEYS)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; expected scene_files (and common, scenes)")
    files = (dataset or {}).get("scene_files")
    if not isinstance(files, list) or not files or not all(
            isinstance(f, str) or (isinstance(f, list) and f and all(isinstance(g, str) for g in f)) for f in files):
        raise ValueError(f"{where}: scene_files must be a non-empty list of scene file paths "
                         f"(or of lists of them, merged in order), got {files!r}")
    common = dataset.get("common") or {}
    if not isinstance(common, dict):
        raise ValueError(f"{where}: common must be a mapping of settings, got {common!r}")
    base_cfg = read_settings(base) if base is not None and Path(base).is_file() else {}
    if common:  # its own errors name it, not the first scene file
        try:
            validate_config(deep_update(base_cfg, common))
        except ValueError as e:
            raise ValueError(f"{where}: common: {e}") from None
    configs: dict[str, dict] = {}
    named_by: dict[str, str] = {}
    for entry in files:
        merged, own = common, {}
        for part in [entry] if isinstance(entry, str) else entry:
            settings = read_settings(part, where, "scene file")
            if not settings:  # it would run the default scene under the scene file's name
                raise ValueError(f"{where}: scene file {part} is empty")
            merged, own = deep_update(merged, settings), deep_update(own, settings)
        f = entry if isinstance(entry, str) else " + ".join(entry)
        if "scene" not in own:  # it would run as the default scene, into its results folder
            raise ValueError(f"{where}: scene file {f} sets no `scene:` (the name of its results "
                             f"folder); without one it would run as {base_cfg.get('scene', 'demo')!r}")
        try:
            # Snakemake's order: the command-line files, the Snakefile's configfile: under them,
            # the command-line files again (the keys of the schema's sections end up in schema
            # order either way; only free-form names such as other_methods' keep this order)
            cfg = validate_config(deep_update(deep_update(merged, base_cfg), merged))
        except ValueError as e:
            raise ValueError(f"{where}: scene file {f}: {e}") from None
        name = cfg["scene"]
        if name in configs:
            raise ValueError(f"{where}: scene files {named_by[name]} and {f} both name scene {name!r} "
                             f"(set a different `scene:` in each: it names the results folder)")
        configs[name], named_by[name] = cfg, f
    return {name: configs[name] for name in _chosen_scenes(list(configs), dataset.get("scenes"), where)}


def _chosen_scenes(names: list[str], chosen, where: str) -> list[str]:
    """The scenes of ``names`` that the dataset's ``scenes`` setting picks, in ``names``' order.

    ``chosen`` is a name, a list of names or None (all). Snakemake's ``--config scenes=tiny``
    parses as a string, ``scenes=[2024]`` as a list of strings and ``scenes=2024`` as an int, so
    every name is compared as a string."""
    if chosen is None:
        return names
    wanted = [str(n) for n in (chosen if isinstance(chosen, list) else [chosen])]
    unknown = [n for n in wanted if n not in names]
    if not wanted or unknown:
        raise ValueError(f"{where}: scenes must name scenes of the dataset ({', '.join(names)}), got {chosen!r}"
                         + (f": {', '.join(map(repr, unknown))} is not one" if unknown else ""))
    return [n for n in names if n in wanted]


def other_method_paths(others) -> dict:
    """``{name: (slices path, uv mesh path or None)}`` of the setting ``evaluation.other_methods``,
    whose values are a path, or ``{slices: path, uv_mesh: path}`` for slices in another UV layout
    (read here once for the evaluation and for the workflow's inputs)."""
    out = {}
    for name, spec in (others or {}).items():
        if isinstance(spec, dict):
            unknown = sorted(set(spec) - {"slices", "uv_mesh"})
            if unknown or "slices" not in spec:
                raise ValueError(f"other method {name!r}: expected a path or {{slices: path, uv_mesh: path}}, "
                                 f"got keys {sorted(spec)}")
            out[name] = (str(spec["slices"]), None if spec.get("uv_mesh") is None else str(spec["uv_mesh"]))
        else:
            out[name] = (str(spec), None)
    return out
