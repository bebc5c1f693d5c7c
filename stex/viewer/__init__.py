"""The 4-D viewer: a finished run as a static web page that plays the tracked mesh with its
per-frame texture (orbit, play/pause, frame slider, the input colour frame beside it, the label
map as an overlay), drawn with three.js vendored in ``static/three``.

- :func:`write_view` (``stex view``, the workflow's ``view`` rule) writes the folder.
- :mod:`stex.viewer.pack` turns the run's arrays into the page's buffers (pure functions).

The page's URL parameters: ``frame=K`` (position in the shown frames, from 0), ``play=1``,
``labels=1`` (overlay on), ``camera=input`` (the input colour camera's exact view, fixed, at
``size=H`` pixels high, 360 by default: the same image as the middle panel of ``stex preview``).
"""

from stex.viewer.write import IMAGE_FORMATS, write_view

__all__ = ["write_view", "IMAGE_FORMATS"]
