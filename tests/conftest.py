import os
from pathlib import Path

import pytest

from stex.config import load_config

REPO = Path(__file__).resolve().parents[1]


def data_samples() -> Path:
    """The shared third-party samples (../shared/data_samples or $STEX_DATA_SAMPLES)."""
    env = os.environ.get("STEX_DATA_SAMPLES")
    return Path(env) if env else REPO.parent / "shared" / "data_samples"


TINY_SYNTHETIC = {
    "n_frames": 6,
    "texture_size": 128,
    "color": {"width": 200, "height": 150, "fx": 175.0},
    "depth": {"width": 100, "height": 90, "fx": 79.0},
    "procedural": {"n_around": 32, "n_rings": 16},
}


@pytest.fixture(scope="session")
def demo_config() -> dict:
    """The embedded default scene's validated config."""
    return load_config(REPO / "config" / "config.yaml")


@pytest.fixture
def tiny_config() -> dict:
    """A tiny synthetic scene (fast to render) with schema defaults."""
    return load_config(overrides={"scene": "tiny", "frame_block": 4,
                                  "source": {"kind": "synthetic", "synthetic": TINY_SYNTHETIC}})
