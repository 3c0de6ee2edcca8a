"""The emulated camera's config keys: derived defaults and one-line errors."""

from __future__ import annotations

import pytest

from hal.config import RigConfig, load_config, plant_view
from hal.errors import HalConfigError


def test_defaults_are_the_papers_camera_at_640x480():
    c = load_config().camera
    assert c.model == "image"
    assert c.true_focal_px == (1230.0, 1230.0)
    assert c.true_principal_point_px == (319.5, 239.5)
    assert c.true_lens == (c.lens_k1, c.lens_k2, c.lens_p1, c.lens_p2, c.lens_k3)


def test_derived_focal_length_follows_the_plants_s_lambda():
    cfg = RigConfig().with_overrides({"plant.s_lambda": 1.1})
    assert plant_view(cfg).camera.true_focal_px == pytest.approx((1353.0, 1353.0))
    explicit = RigConfig().with_overrides({"camera.focal_px": [1200.0, 1210.0]})
    assert explicit.camera.true_focal_px == (1200.0, 1210.0)


def test_principal_point_follows_the_resolution_unless_given():
    cfg = RigConfig().with_overrides({"camera.width_px": 1280, "camera.height_px": 1024})
    assert cfg.camera.true_principal_point_px == (639.5, 511.5)
    cfg = cfg.with_overrides({"camera.principal_point_px": [600.0, 500.0]})
    assert cfg.camera.true_principal_point_px == (600.0, 500.0)


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"camera.model": "photo"}, "camera.model: must be image or analytic"),
        ({"camera.principal_point_px": [640.0, 10.0]}, "must lie inside the 640x480 image"),
        ({"camera.principal_point_px": [0.0, 10.0]}, "camera.principal_point_px: must be (0, 0)"),
        ({"camera.focal_px": [1230.0, 0.0]}, "camera.focal_px: must be (0, 0)"),
        ({"camera.width_px": 8}, "camera.width_px"),
        ({"camera.width_px": 640.5}, "expected an integer"),
        ({"camera.exposure_s": -0.001}, "camera.exposure_s"),
        ({"camera.read_noise_dn": 300.0}, "camera.read_noise_dn"),
        ({"camera.lens_p1": 2.0}, "camera.lens_p1"),
    ],
)
def test_bad_camera_settings_are_one_line_errors(overrides, message):
    with pytest.raises(HalConfigError) as err:
        RigConfig().with_overrides(overrides)
    assert message in str(err.value)
    assert "\n" not in str(err.value)
