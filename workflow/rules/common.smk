# Paths, frame blocks and parameter sections shared by the rules.
from stex.config import check_relations, other_method_paths, scoring_settings
from stex.ingest import frame_blocks, open_source
from stex.io import id_ranges

check_relations(config)  # what the schema cannot say (e.g. masks.depth_near_m < depth_far_m)
RESULTS = f"{config['results']}/{config['scene']}"
# only the active kind's settings: they are the ingest jobs' parameters, and a setting of another
# kind (or a key newly added to one) must not re-run a finished scene
_KIND = config["source"]["kind"]
SOURCE = {"kind": _KIND, _KIND: config["source"][_KIND]}
SYNTHETIC = _KIND == "synthetic"
try:
    _SOURCE = open_source(SOURCE)
except (OSError, ValueError) as e:  # in a dataset run, say which scene's source it is
    raise type(e)(f"scene {config['scene']!r}: {e}") from None
BLOCKS = frame_blocks(len(_SOURCE.frame_ids), config["frame_block"])
BLOCK_IDS = [f"{b:04d}" for b in range(len(BLOCKS))]
ENV = "../../envs/stex.yaml"
# Wall time (minutes) asked of a cluster by the jobs that run over the whole sequence (a local run
# ignores it; other jobs get the profile's default). At paper scale, 265 frames: tracking 6.1,
# texcoords 1.9, the sampling table 12.1, labeling 3.9 min (docs/paper_scale.md); 240 leaves room for a few
# thousand frames. In the rules rather than the profile, so that it holds for prefixed rule names
# too (workflow/dataset.smk).
SEQUENCE_RUNTIME_MIN = 240
# Snakemake priority of the jobs that make the texture (ingest to correction); the extras (the
# sampling table, the previews, the comparison methods, the evaluation, the preview video) keep
# the default 0. When both are ready and the cores are taken, the texture goes first: left to
# itself Snakemake may start the optional job first and the texture waits for it.
TEXTURE_PRIORITY = 10
OPTIMISED = config["observations"]["coordinates"] == "optimised"
# texture coordinates every stage after the projection samples: ξ, or Φ as an ablation
COORDS = f"{RESULTS}/texcoords.zarr" if OPTIMISED else f"{RESULTS}/projection.zarr"
# the paper's sampling table (the texcoords stage again per key-frame step), in the evaluation
SAMPLING = [f"{RESULTS}/texcoords_sampling.json"] if OPTIMISED and config["sampling_table"]["steps"] else []
# other methods' texture slices (and the meshes of their UV layouts) scored beside ours
# (evaluation.other_methods: {name: path or {slices, uv_mesh}})
OTHER_METHODS = [
    p for pair in other_method_paths(config["evaluation"].get("other_methods")).values() for p in pair if p
]
# reference methods the workflow builds (evaluation.references, workflow/rules/references.smk),
# scored as other methods of their names
REFERENCES = list(config["evaluation"].get("references") or [])
if not SYNTHETIC and {"oracle", "oracle_candidates"} & set(REFERENCES):
    raise ValueError(f"scene {config['scene']!r}: evaluation.references oracle needs the truth of a synthetic scene")
_clash = sorted(set(REFERENCES) & set(config["evaluation"].get("other_methods") or {}))
if _clash:
    raise ValueError(f"config error at evaluation/other_methods: {_clash} are names of evaluation.references")
EVALUATION = dict(
    config["evaluation"],
    other_methods={
        **(config["evaluation"].get("other_methods") or {}),
        **{r: f"{RESULTS}/references/{r}/corrected" for r in REFERENCES},
    },
)
REFERENCE_BLOCKS = [
    f"{RESULTS}/references/{r}/corrected/block_{b:04d}.zarr" for r in REFERENCES for b in range(len(BLOCKS))
]


wildcard_constraints:
    block=r"\d{4}",


def block_range(wildcards):
    """[start, stop) frame positions of a frame block."""
    return list(BLOCKS[int(wildcards.block)])


def scene_source_files(wildcards):
    """The dataset files the scene store is read from (calibration, template, given meshes)."""
    return [str(p) for p in _SOURCE.files()]


def block_source_files(wildcards):
    """The dataset files a frame block is read from (its frames' images; the calibration)."""
    return [str(p) for p in _SOURCE.files(*BLOCKS[int(wildcards.block)])]


def all_outputs():
    out = [f"{RESULTS}/scene.zarr", f"{RESULTS}/previews/masks.png"]
    out += [f"{RESULTS}/template.zarr", f"{RESULTS}/previews/template_atlas.png"]
    out += [f"{RESULTS}/tracking.zarr", f"{RESULTS}/previews/tracking_fit.png", f"{RESULTS}/poses.zarr"]
    out += [f"{RESULTS}/projection.zarr", f"{RESULTS}/previews/projection.png"]
    out += [COORDS, f"{RESULTS}/observations.zarr", f"{RESULTS}/labels.zarr"]
    if OPTIMISED:
        out += [f"{RESULTS}/previews/texcoords.png"]
    # every block store is a target: a deleted one (which `stex evaluate` and `stex export
    # --source volume` read) is rebuilt even when nothing after it changed
    out += expand(
        f"{RESULTS}/{{kind}}/block_{{block}}.zarr", kind=["data_term", "volume", "corrected"], block=BLOCK_IDS
    )
    out += [f"{RESULTS}/previews/labels.png", f"{RESULTS}/previews/preview.mp4", f"{RESULTS}/view"]
    out += [f"{RESULTS}/global_texture.zarr", f"{RESULTS}/evaluation"]
    out += expand(f"{RESULTS}/frames/block_{{block}}.zarr", block=BLOCK_IDS)
    out += expand(f"{RESULTS}/masks/block_{{block}}.zarr", block=BLOCK_IDS)
    if SYNTHETIC:
        out += expand(f"{RESULTS}/truth/block_{{block}}.zarr", block=BLOCK_IDS)
    return out


def previous_corrected(wildcards):
    """The previous block's corrected store when the temporal coupling chains the blocks."""
    b = int(wildcards.block)
    if not config["correction"]["temporal"] or b == 0:
        return []
    return [f"{RESULTS}/corrected/block_{b - 1:04d}.zarr"]


def evaluation_blocks(kind):
    """Input function: the ``kind`` block stores a frame block's scoring reads: its own and the
    previous block's (the flicker of its first frame compares it with its predecessor)."""

    def blocks(wildcards):
        b = int(wildcards.block)
        return [f"{RESULTS}/{kind}/block_{k:04d}.zarr" for k in range(max(0, b - 1), b + 1)]

    return blocks


def previous_reference_corrected(wildcards):
    """The previous block's corrected store of the reference when the temporal coupling chains the blocks."""
    b = int(wildcards.block)
    if not config["correction"]["temporal"] or b == 0:
        return []
    return [f"{RESULTS}/references/{wildcards.reference}/corrected/block_{b - 1:04d}.zarr"]
