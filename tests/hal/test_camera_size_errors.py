"""A bad camera image size is its own key's range error, whatever the sign: the principal
point's "inside the image" rule is checked only on a valid size."""

from __future__ import annotations

from pathlib import Path

import pytest

from hal.config import load_config
from hal.errors import HalConfigError


@pytest.mark.parametrize(
    ("key", "value"),
    [("width_px", 0), ("width_px", -640), ("height_px", -480), ("height_px", 8)],
)
def test_an_image_size_out_of_range_names_its_own_key(tmp_path: Path, key: str, value: int):
    path = tmp_path / "rig.toml"
    path.write_text(f"[camera]\n{key} = {value}\n")
    with pytest.raises(HalConfigError) as err:
        load_config(path)
    assert f"camera.{key}: {value} is out of range [16, 8192]" in str(err.value)
