"""stex — spatiotemporal texture reconstruction from one RGB-D camera and a template mesh.

The pipeline as stage functions, one module a stage. Each is pure (numpy arrays in, arrays out);
``stex.stages.<stage>.write_*`` opens the stage's input stores, calls it and writes its store,
and the Snakemake workflow (``workflow/``) calls those through thin scripts.

1.  ``ingest.open_source``          — a synthetic scene, a folder dataset or an Azure Kinect .mkv
    as frames of colour, depth and calibration (``stex.readers``, ``stex.synth``).
2.  ``masks.compute_mask``          — a GrabCut foreground mask per frame seeded from the depth
    range, optionally without the support plane.
3.  ``template.prepare_template``   — the template cleaned and decimated (or made from the first
    frame's depth), its UV atlas and texel map (``stex.mesh``, ``stex.atlas``).
4.  ``tracking.track_sequence``     — the template's vertices at every frame: embedded
    deformation + L0 through the depth stream with an optical-flow term
    (``stex.deformation``, ``stex.flow``).
5.  ``poses.pose_table``            — the rigid motion K_{t->t'} between frame pairs (E_glo).
6.  ``projection.project_frame``    — Φ: the tracked mesh in a colour image, which vertices and
    faces it sees, at what cosine.
7.  ``texcoords.optimize_texcoords`` — ξ: Φ refined so that every frame's samples of a face agree
    (Kim et al. 2019; ``stex.photometric``).
8.  ``global_texture.global_texture`` — the baseline: one texture blended from every source frame.
9.  ``observations.face_samples``   — what each frame shows of each face: grey samples, E_qual,
    SSIM dynamism (``stex.dynamism``), SHOT descriptors and strain (``stex.similarity``).
10. ``data_term.block_candidates``  — per target frame and face the candidate source frames and
    the data term E_qual + ω_g E_glo + (1 − ω_g) E_loc + ω_str E_str.
11. ``labeling.label_sequence``     — the spatiotemporal MRF of Eq. 2: α-expansion per frame
    (``stex.mrf``, ``stex.maxflow``), block coordinate descent over the frames.
12. ``volume.volume_slice``         — one atlas slice per frame from the labelled source frames,
    never-seen faces filled (``stex.sampling``).
13. ``correction.CorrectionSystem`` — gradient-domain colour correction of every slice.
14. ``evaluation.score_methods``    — every method scored by the same code (``stex.metrics``)
    against the input views and, for synthetic scenes, the truth.

Shared leaves: ``stex.camera`` (conventions, projection), ``stex.render`` (rasteriser,
visibility), ``stex.image`` (grey levels). Files: ``stex.export`` (PNG, MP4, OBJ, glTF writers),
``stex.io`` and ``stex.artifacts`` (the stores and what each holds), ``stex.cli`` (the ``stex``
command). docs/architecture.md has the artifact flow and where each kind of change goes.
"""

__version__ = "0.1.0"
