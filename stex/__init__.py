"""stex — spatiotemporal texture reconstruction from one RGB-D camera and a template mesh.

The pipeline, one module per stage (each a set of pure functions over numpy arrays; the
Snakemake workflow in ``workflow/`` calls them through thin scripts):

1. ``stex.ingest``   — read a folder dataset, an Azure Kinect .mkv or a synthetic scene into
   the ``scene`` and per-block ``frames`` stores (``stex.readers``, ``stex.synth``).
2. ``stex.masks``    — GrabCut foreground masks at colour resolution, seeded from depth.
3. ``stex.template`` — clean and decimate (or subdivide) the template, build its UV atlas
   (xatlas, mirrored charts fixed), face adjacency and the texel -> face map.
4. ``stex.tracking`` — template vertices at every frame: embedded deformation with the L0
   motion regulariser through the depth stream (plus an optical-flow term), or given meshes.
5. ``stex.poses``    — rigid poses K_{t->t'} between all frame pairs (RANSAC + ICP).

Shared building blocks: ``stex.camera`` (conventions, projection), ``stex.render`` (numba
rasteriser, visibility, textured rendering), ``stex.io`` (the artifact stores and their layout).
"""

__version__ = "0.1.0"
