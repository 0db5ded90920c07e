"""Which water model a spec gets: physical by default, the paper's where the spec was written for it, always named
in the validated spec so its canonical form (digest, meta, the service's copy) cannot read differently later."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from seasynth.service.spec.dataset import DatasetSpec, spec_digest

PAPER_ONLY = {
    "beta_D": {"min": [0.1] * 3, "max": [0.1] * 3},
    "beta_B": {"min": [0.1] * 3, "max": [0.1] * 3},
    "B_inf": {"min": [0.1] * 3, "max": [0.1] * 3},
    "backscatter_ratio": [0.8, 1.0],  # the default value, given: still written for the paper's model
    "B_inf_jitter": [0.8, 1.2],
}
HIGH_CAMERA = {"camera": {"min": [-1.0, -1.0, 1.0], "max": [1.0, 1.0, 6.0]}}


def test_unset_model_is_physical():
    assert DatasetSpec().water.model == "physical"
    assert DatasetSpec.model_validate({"water": {"jerlov": ["II"]}}).water.model == "physical"


@pytest.mark.parametrize("field", sorted(PAPER_ONLY))
def test_a_paper_only_field_keeps_the_paper_model(field):
    assert DatasetSpec.model_validate({"water": {field: PAPER_ONLY[field]}}).water.model == "paper"


def test_a_camera_reaching_the_default_surface_keeps_the_paper_model_unless_depth_is_given():
    assert DatasetSpec.model_validate({"workspaces": HIGH_CAMERA}).water.model == "paper"
    with pytest.raises(ValidationError, match=r"water\.depth_m: min 5\.0 m puts the surface"):
        DatasetSpec.model_validate({"workspaces": HIGH_CAMERA, "water": {"depth_m": [5.0, 20.0]}})
    deep = DatasetSpec.model_validate({"workspaces": HIGH_CAMERA, "water": {"depth_m": [8.0, 20.0]}})
    assert deep.water.model == "physical"
    survey = {"kind": "lawnmower", "altitude_m": 6.0}
    assert DatasetSpec.model_validate({"trajectory": survey}).water.model == "paper"


def test_an_explicit_model_is_kept_and_contradicting_fields_name_it():
    assert DatasetSpec.model_validate({"water": {"model": "paper"}}).water.model == "paper"
    with pytest.raises(ValidationError, match=r"beta_D belongs to the paper model, but water.model is physical"):
        DatasetSpec.model_validate({"water": {"model": "physical", "beta_D": PAPER_ONLY["beta_D"]}})
    with pytest.raises(ValidationError, match=r"absorption belongs to the physical model, but water.model resolves"):
        DatasetSpec.model_validate({"water": {"absorption": PAPER_ONLY["beta_D"], "B_inf": PAPER_ONLY["B_inf"]}})


@pytest.mark.parametrize("water", [{}, {"backscatter_ratio": [0.8, 1.0]}, {"B_inf_jitter": [0.8, 1.2]}])
def test_the_canonical_form_names_the_model_so_a_round_trip_keeps_it(water):
    spec = DatasetSpec.model_validate({"water": water})
    canon = spec.model_dump(mode="json", exclude_defaults=True)
    assert canon["water"]["model"] == spec.water.model
    again = DatasetSpec.model_validate(canon)
    assert again.water.model == spec.water.model and spec_digest(again) == spec_digest(spec)


@pytest.mark.parametrize("water", [{"model": "paper"}, {"enabled": False}])
def test_lamps_need_the_physical_model(water):
    with pytest.raises(ValidationError, match=r"lighting\.lamps: lamps are part of the physical light model"):
        DatasetSpec.model_validate({"water": water, "lighting": {"lamps": [{}]}})
