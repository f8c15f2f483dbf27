"""workbench.core.options: the values an options field declares are the values it takes, for every options class."""

from __future__ import annotations

import dataclasses
import math

import pytest

from workbench.core.camera import LensPrior
from workbench.core.options import Range, field_checks, check_options
from workbench.errors import SettingsError
from workbench.export.scene import ExportOptions
from workbench.georef.options import LOSSES, GeorefOptions
from workbench.intrinsics.sfm import CAMERA_MODELS, MATCHERS, SfmOptions
from workbench.stitch.bundle_problem import BundleOptions

BASE = {GeorefOptions: {}, SfmOptions: {}, ExportOptions: {},
        BundleOptions: {"fixed_intrinsics": False, "estimate_k1": True},
        LensPrior: {"focal_rel": 0.05, "principal_point_rel": 0.05, "k1": 0.25, "k2": 0.25}}


def _edges(rule: Range, integer: bool) -> tuple[list, list]:
    """Values just inside and just outside each bound of ``rule``."""
    step = 1 if integer else 1e-9
    inside, outside = [], []
    for bound, sign, closed in ((rule.gt, 1, False), (rule.ge, 1, True), (rule.lt, -1, False), (rule.le, -1, True)):
        if bound is None:
            continue
        edge = int(bound) if integer else float(bound)
        inside.append(edge if closed else edge + sign * step)
        outside.append(edge - sign * step if closed else edge)
    return [v for v in inside if rule.holds(v)], [v for v in outside if v not in rule.also]


@pytest.mark.parametrize("cls", list(BASE), ids=lambda c: c.__name__)
def test_every_declared_bound_is_enforced_on_both_sides(cls):
    checks = field_checks(cls)
    assert len(checks) >= 4  # each of these classes declares what most of its fields take
    for name, kind, rule in checks:
        if kind == "choice":
            cls(**{**BASE[cls], name: rule[-1]})
            with pytest.raises(SettingsError, match=f"{name} = 'no-such-choice'"):
                cls(**{**BASE[cls], name: "no-such-choice"})
            continue
        inside, outside = _edges(rule, kind == "int")
        assert inside and outside, name
        for v in inside:
            assert getattr(cls(**{**BASE[cls], name: v}), name) == v
        for v in outside:
            with pytest.raises(SettingsError, match=f": {name} = "):
                cls(**{**BASE[cls], name: v})
        with pytest.raises(SettingsError, match=name):
            cls(**{**BASE[cls], name: math.nan if kind == "range" else True})


def test_messages_name_the_options_the_key_the_value_and_the_domain():
    with pytest.raises(SettingsError, match=r"^georef options: model_min_points = 2: must be an integer >= 3$"):
        GeorefOptions(model_min_points=2)
    with pytest.raises(SettingsError, match=r"^sfm options: sift_peak_threshold = 0.0: must be in \(0, 0.1\)$"):
        SfmOptions(sift_peak_threshold=0.0)
    with pytest.raises(SettingsError, match=r"^export options: terrain_max_faces = 999: must be 0 or an integer >= 1000$"):
        ExportOptions(terrain_max_faces=999)
    with pytest.raises(SettingsError, match=r"must be one of \['linear', 'huber', 'soft_l1', 'cauchy'\]"):
        GeorefOptions(loss="l2")
    with pytest.raises(SettingsError, match=r"^lens prior: k2 = -0.1: must be > 0$"):
        LensPrior(focal_rel=0.05, principal_point_rel=0.05, k1=0.25, k2=-0.1)
    assert ExportOptions(terrain_max_faces=0).terrain_max_faces == 0  # the value taken outside the range
    with pytest.raises(SettingsError, match="max_points = 1.5: must be an integer"):
        SfmOptions(max_points=1.5)
    with pytest.raises(SettingsError, match="seed = '0'"):
        GeorefOptions(seed="0")


def test_choices_are_the_literal_types():
    assert LOSSES == ("linear", "huber", "soft_l1", "cauchy")
    assert "RADIAL" in CAMERA_MODELS and "auto" in MATCHERS


def test_range_words():
    assert Range(gt=0).describe(False) == "> 0"
    assert Range(ge=2).describe(True) == "an integer >= 2"
    assert Range(ge=0, lt=1).describe(False) == "in [0, 1)"
    assert Range(gt=0, le=1).describe(False) == "in (0, 1]"
    assert Range(ge=1000, also=(0,)).describe(True) == "0 or an integer >= 1000"


def test_fields_without_a_declaration_are_not_checked():
    @dataclasses.dataclass(frozen=True)
    class Free:
        x: float = 1.0

        def __post_init__(self) -> None:
            check_options(self, "free")

    assert Free(x=-5.0).x == -5.0
