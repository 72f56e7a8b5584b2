"""Study ``seeking``'s outcome lines say why a family has no verdict."""

import pandas as pd

from esa_experiments.studies.seeking import arm_labels, outcomes

PICKS = {"ppo": {"learner": "ppo_fit_quadratic", "kappa": 1.0}, "off_policy": None}


def test_a_family_e1_closed_is_reported_closed_and_one_without_seeds_as_pending():
    empty = pd.DataFrame(columns=["family", "env", "method", "against", "verdict"])

    text = outcomes(empty, empty, arm_labels(PICKS), PICKS)

    assert "- **ppo**: no verdict yet (its ESA arm has no two seeds)." in text
    for family in ("sac", "td3"):
        assert f"- **{family}**: closed by E1" in text
        assert f"ESA is not shown to help {family.upper()}." in text
