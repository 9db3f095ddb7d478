"""Net mesh geometry: the cell area the plane fit divides by, and its validation."""

from __future__ import annotations

import math

import pytest

from service.core.errors import ConfigError
from service.core.mesh import MeshGeometry


def test_square_mesh_cell_is_bar_length_squared() -> None:
    assert MeshGeometry(bar_length_m=0.015).cell_area_m2 == pytest.approx(0.015**2, rel=1e-12)


@pytest.mark.parametrize("angle", [30.0, 60.0, 75.0, 120.0])
def test_rhombic_cell_area_from_its_diagonals(angle: float) -> None:
    # Independent formula: a rhombus of side L and interior angle a has diagonals
    # 2 L cos(a/2) and 2 L sin(a/2); its area is half their product.
    bar = 0.02
    half = math.radians(angle) / 2
    expected = 0.5 * (2 * bar * math.cos(half)) * (2 * bar * math.sin(half))
    assert MeshGeometry(bar, opening_angle_deg=angle).cell_area_m2 == pytest.approx(expected)


def test_supplementary_opening_angles_give_the_same_cell() -> None:
    # A rhombus with angle a also has angle 180 - a: the same net hung the other way round.
    hung_one_way = MeshGeometry(0.02, 60.0).cell_area_m2
    assert hung_one_way == pytest.approx(MeshGeometry(0.02, 120.0).cell_area_m2)


@pytest.mark.parametrize(
    ("kwargs", "key"),
    [
        ({"bar_length_m": 0.0}, "mesh.bar_length_m"),
        ({"bar_length_m": -0.015}, "mesh.bar_length_m"),
        ({"bar_length_m": math.nan}, "mesh.bar_length_m"),
        ({"bar_length_m": 15.0}, "mesh.bar_length_m"),  # centimetres typed as metres
        ({"bar_length_m": 0.015, "opening_angle_deg": 0.0}, "mesh.opening_angle_deg"),
        ({"bar_length_m": 0.015, "opening_angle_deg": 180.0}, "mesh.opening_angle_deg"),
        ({"bar_length_m": 0.015, "opening_angle_deg": math.nan}, "mesh.opening_angle_deg"),
    ],
)
def test_invalid_mesh_raises_config_error_naming_the_key(
    kwargs: dict[str, float], key: str
) -> None:
    with pytest.raises(ConfigError) as err:
        MeshGeometry(**kwargs)
    assert err.value.key == key
    assert str(err.value).startswith(key)
