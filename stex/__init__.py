"""stex — spatiotemporal texture reconstruction from one RGB-D camera and a template mesh.

The pipeline, one module per stage (each a set of pure functions over numpy arrays; the
Snakemake workflow in ``workflow/`` calls them through thin scripts):

1. ``stex.ingest``   — read a folder dataset, an Azure Kinect .mkv or a synthetic scene into
   the ``scene`` and per-block ``frames`` stores (``stex.readers``, ``stex.synth``).
2. ``stex.masks``    — GrabCut foreground masks at colour resolution, seeded from depth
   (optionally without the support plane the object stands on).
3. ``stex.template`` — clean and decimate (or subdivide) the template (or build one from the
   first frame's depth), build its UV atlas (xatlas, mirrored charts fixed), face adjacency and
   the texel -> face map.
4. ``stex.tracking`` — template vertices at every frame: embedded deformation with the L0
   motion regulariser through the depth stream (plus an optical-flow term), or given meshes.
5. ``stex.poses``    — rigid poses K_{t->t'} between all frame pairs (RANSAC + ICP).
6. ``stex.projection`` — Φ: the tracked mesh in every colour image, visibility and cosines.
7. ``stex.texcoords`` — ξ: texture coordinates optimised so all frames agree (Kim et al. 2019).
8. ``stex.observations`` — one pass over the frames: grey samples per face and shared edge,
   E_qual flags, SSIM dynamism (``stex.dynamism``), SHOT descriptors and face strain
   (``stex.similarity``).
9. ``stex.data_term``   — per target frame and face the candidate source frames and the data term
   (E_qual + ω_g E_glo + (1 − ω_g) E_loc + ω_str E_str; the similarities from
   ``stex.similarity``).
10. ``stex.labeling`` — the spatiotemporal MRF: α-expansion per frame (``stex.mrf``), block
    coordinate descent over even/odd frames, selective weighting.
11. ``stex.volume``  — one atlas slice per frame from the labelled source frames; never-seen
    faces filled; gutter dilated.
12. ``stex.correction`` — gradient-domain colour correction of every slice (screened Poisson;
    the slice's own frame's texels kept, the borrowed ones corrected towards them).
13. ``stex.export``  — PNG slices, MP4, OBJ/glTF per frame, preview videos.

Baselines: ``stex.global_texture`` (Kim et al. 2019's global texture, naive projection). Metrics:
``stex.metrics``; the evaluation stage ``stex.evaluation`` (other methods' textures in another
UV layout carried into the run's atlas by ``stex.resample``). Shared building blocks: ``stex.camera`` (conventions, projection),
``stex.render`` (numba rasteriser, visibility, textured rendering), ``stex.io`` (the artifact
stores and their layout), ``stex.isolated`` (xatlas run in a child process, whose atlas is never
destroyed: the destructor can hang).
"""

__version__ = "0.1.0"
