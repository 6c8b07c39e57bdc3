"""Tests for soc_opt/mstep/recipe.py: the M-step recipe builds the feasible set from the current
policy and runs exactly the M-step its fields name."""

import numpy as np
import pytest

from soc_opt import estep, mstep
from soc_opt.config import ConfigError
from soc_opt.mstep import MStepConstraints, MStepRecipe
from soc_opt.testing import random_estep_instance


def test_recipe_constraints_are_the_scaled_floor_or_the_entropy_floor_of_the_policy():
    rng = np.random.default_rng(2)
    model, policy, _, _ = random_estep_instance(rng, 2, 1, 4)
    floor = MStepRecipe(cov_floor_scale=0.25).constraints(policy)
    np.testing.assert_array_equal(floor.resolve(1, 4).Smin, 0.25 * np.asarray(policy.cov))
    ent = MStepRecipe(entropy_floor=True, trust_region=0.3).constraints(policy)
    np.testing.assert_array_equal(ent.resolve(1, 4).c, np.linalg.slogdet(policy.cov)[1])
    assert ent.trust_region == 0.3 and ent.cov_floor is None


def test_recipe_maximize_is_the_m_step_with_the_recipes_settings():
    rng = np.random.default_rng(4)
    model, policy, mu0, P0 = random_estep_instance(rng, 2, 1, 5)
    y = rng.uniform(0.1, 1.0, size=5)
    sm = estep.smooth(model, policy, y, mu0, P0)
    recipe = MStepRecipe(cov_floor_scale=0.5, variant="time_invariant")
    got = recipe.maximize(model, sm, y, previous=policy)
    ref = mstep.maximize(model, estep.moments(sm, y), constraints=MStepConstraints(cov_floor=(0.5 * np.asarray(policy.cov)).tolist()),
                         variant="time_invariant", previous=policy, min_norm=True).policy
    np.testing.assert_array_equal(got.K, ref.K)
    np.testing.assert_array_equal(got.cov, ref.cov)


def test_recipe_rejects_unknown_names_at_construction():
    with pytest.raises(ConfigError, match="variant"):
        MStepRecipe(variant="sideways")
