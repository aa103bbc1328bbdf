"""Unit layer of the rules' declared settings (physgrad.optim.capabilities.check_settings): a value
out of a setting's range is refused in one line where the rule is built, before any job, instead of
ending a run as "failed: ValueError"."""

import pytest

from physgrad.errors import UserError
from physgrad.optim.capabilities import SETTINGS, check_settings

SOAP = "physgrad.optim.soap.soap"
PSGD = "physgrad.optim.psgd.psgd_kron"


@pytest.mark.parametrize(
    "target, key, value, said",
    [
        (SOAP, "precondition_frequency", 0, "a whole number of 1 or more"),
        (SOAP, "precondition_frequency", 2.5, "a whole number of 1 or more"),
        (SOAP, "max_precondition_dim", 0, "a whole number of 1 or more"),
        (PSGD, "preconditioner_update_probability", 2, "a probability in (0, 1]"),
        (PSGD, "preconditioner_update_probability", -0.5, "a probability in (0, 1]"),
        (PSGD, "b1", 1.5, "a number in [0, 1)"),
        (PSGD, "max_size_triangular", -1, "a whole number of 1 or more"),
        (PSGD, "grad_clip_max_amp", 0, "a number above 0"),
        ("optax.adam", "eps", float("nan"), "a number above 0"),
        ("optax.adam", "b2", True, "a number in [0, 1)"),
    ],
)
def test_a_setting_out_of_its_range_is_refused_in_one_line(target, key, value, said):
    with pytest.raises(UserError) as caught:
        check_settings({"_target_": target, "name": "rule", key: value})
    message = str(caught.value)
    assert f"optim.{key}={value} is not allowed for optim=rule: give {said}" == message


def test_the_presets_and_null_pass():
    """Every preset of conf/optim passes, every declared setting at a value inside its range and
    null (the rule's default) pass, and a rule without declared settings passes whatever it is
    given."""
    from omegaconf import OmegaConf

    from tests.helpers import REPO

    inside = {"decay": 0.9, "positive": 1e-8, "count": 10, "probability": 1.0}
    for target, keys in SETTINGS.items():
        check_settings({"_target_": target, **{k: inside[kind] for k, kind in keys.items()}})
        check_settings({"_target_": target, **dict.fromkeys(keys)})
    for path in sorted((REPO / "conf" / "optim").glob("*.yaml")):
        check_settings(OmegaConf.to_container(OmegaConf.load(path)))  # read as Hydra reads it
    check_settings({"_target_": "mylab.rule", "b1": 7})
