"""The one validator of method options (MethodOverrides): API schema, worker documents and CLI --option alike."""

from __future__ import annotations

from dataclasses import fields

import pytest

from api.schemas import ReprocessOptions
from cli.commands_offline import _parse_options
from services.core.method_options import MethodOverrides, check_overrides, parse_options
from services.core.methods import MethodOptions

CANARY = "CANARY7741"


def test_every_method_option_but_its_name_is_validated() -> None:
    assert set(MethodOverrides.model_fields) == {f.name for f in fields(MethodOptions)} - {"name"}
    assert ReprocessOptions.model_fields["method_options"].annotation == MethodOverrides | None


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"min_inliers": CANARY}, "method_options: min_inliers must be a whole number"),
        ({"min_inliers": 2.5}, "method_options: min_inliers must be a whole number"),
        ({"min_inliers": 10**9}, "method_options: min_inliers must be <= 100000"),
        ({"neighbours": 10**6}, "method_options: neighbours must be <= 32"),  # the counts that cost work per frame
        ({"target_features": 10**6}, "method_options: target_features must be <= 10000"),
        ({"max_features": 10**6}, "method_options: max_features must be <= 20000"),
        ({"refine_every": 0}, "method_options: refine_every must be >= 1"),
        ({"sift_finest_octave": 3}, "method_options: sift_finest_octave must be <= 0"),
        ({"ransac_px": 1e9}, "method_options: ransac_px must be <= 50"),
        ({"refine": 1}, "method_options: refine must be a boolean"),
        ({"ransac_px": "2"}, "method_options: ransac_px must be a number"),
        ({"ransac_px": -97741.25}, "method_options: ransac_px must be >= 0"),
        ({"ratio": float("nan")}, "method_options: ratio must be a finite number"),
        ({"ratio": 1.5}, "method_options: ratio must be <= 1"),
        ({"vein_scale": 0.0}, "method_options: vein_scale must be > 0"),
        ({"features": CANARY}, "method_options: features must be one of 'sift'"),
        ({CANARY: 1}, "method_options: unknown option; expected some of"),
        ({"name": CANARY}, "method_options: 'name' cannot be overridden"),
    ],
)
def test_refusals_name_the_field_and_constraint_never_the_value(overrides: dict, message: str) -> None:
    with pytest.raises(ValueError) as err:
        check_overrides(overrides)
    assert str(err.value).startswith(message), str(err.value)
    assert CANARY not in str(err.value) and "97741" not in str(err.value)
    with pytest.raises(ValueError, match="method_options"):  # the workers' reading of options.json
        parse_options({"method_options": overrides}, strict=False)


def test_valid_overrides_keep_only_what_was_given() -> None:
    assert check_overrides({"ransac_px": 3, "min_inliers": 12}) == {"ransac_px": 3.0, "min_inliers": 12}
    assert check_overrides(None) == {} and check_overrides({}) == {}
    assert check_overrides({"sift_finest_octave": -1, "neighbours": 32}) == {"sift_finest_octave": -1, "neighbours": 32}
    opts, _ = parse_options({"method": "paper", "method_options": {"ransac_px": 3}})
    assert opts.ransac_px == 3.0 and isinstance(opts.ransac_px, float) and opts.features == "modified-asift"


def test_cli_options_are_converted_and_validated_by_the_same_model() -> None:
    parsed = _parse_options(["refine=false", "features=asift", "min_inliers=7", "ransac_px=2.5"])
    assert parsed == {"refine": False, "features": "asift", "min_inliers": 7, "ransac_px": 2.5}
    for bad, needle in [
        (["refine=maybe"], "refine must be a boolean"),
        (["min_inliers=-1"], "min_inliers must be >= 0"),
        (["turbo=1"], "unknown option"),
        (["features"], "expected KEY=VALUE"),
    ]:
        with pytest.raises(ValueError, match=needle):
            _parse_options(bad)
