"""Real-time chunking guidance (lq_ros/core/rtc_guidance.py) on a flow whose exact velocity field is known."""

import math

import numpy as np
import pytest

from lq_ros.core.merge import ActionPrefix
from lq_ros.core.rtc_guidance import MAX_GUIDANCE, guidance_weight, guided_sample, inpaint_chunk, prefix_weights

torch = pytest.importorskip("torch")
H = 8


def gaussian_flow(sigma: float = 1.0, eps: float = 0.05):
    """Exact velocity of the rectified flow from N(0, I) to chunks x1 ~ N(0, sigma^2 11^T + eps^2 I): every
    row of a chunk shares one latent, so knowing some rows determines the others (what inpainting uses).
    x_t = t x1 + (1 - t) x0, v = E[x1 - x0 | x_t] = (t S - (1 - t) I)(t^2 S + (1 - t)^2 I)^-1 x_t."""
    eye = torch.eye(H, dtype=torch.float64)
    cov = sigma**2 * torch.ones(H, H, dtype=torch.float64) + eps**2 * eye

    def velocity(x, t):
        m = (t * cov - (1 - t) * eye) @ torch.linalg.inv(t * t * cov + (1 - t) ** 2 * eye)
        return torch.einsum("ij,bjd->bid", m, x)

    return velocity


def euler(velocity, noise, steps):
    """The unguided sampler (lq_ros/training/models.integrate's schedule)."""
    x, dt = noise, 1.0 / steps
    for k in range(steps):
        x = x + dt * velocity(x, k * dt)
    return x


def test_prefix_weights_match_the_reference_schedules():
    # kinetix get_prefix_weights' docstring: start 2, end 6, total 10, linear.
    np.testing.assert_allclose(prefix_weights(2, 6, 10, "linear"), [1, 1, 0.8, 0.6, 0.4, 0.2, 0, 0, 0, 0])
    c = np.array([1, 1, 0.8, 0.6, 0.4, 0.2])
    np.testing.assert_allclose(prefix_weights(2, 6, 10, "exp")[:6], c * np.expm1(c) / (math.e - 1))
    assert prefix_weights(2, 6, 10, "hard").tolist() == [1, 1, 0, 0, 0, 0, 0, 0, 0, 0]
    assert prefix_weights(2, 6, 10, "ones").tolist() == [1] * 6 + [0] * 4
    # The plan ends first: only its rows guide.
    np.testing.assert_allclose(prefix_weights(4, 2, 10, "exp"), [1, 1] + [0] * 8)
    assert prefix_weights(0, 0, 10, "exp").tolist() == [0] * 10  # nothing planned: unguided
    with pytest.raises(ValueError):
        prefix_weights(1, 2, 3, "soft")


def test_guidance_weight_schedule():
    assert guidance_weight(0.0) == MAX_GUIDANCE
    assert guidance_weight(0.9) == MAX_GUIDANCE  # capped
    assert guidance_weight(0.9, 100.0) == pytest.approx(0.1 / 0.9 * (0.81 + 0.01) / 0.01)
    assert guidance_weight(0.5) == pytest.approx(2.0) and 2.0 < MAX_GUIDANCE


def test_zero_weights_give_the_unguided_chunk_exactly():
    velocity = gaussian_flow()
    noise = torch.randn((1, H, 1), generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    out = guided_sample(velocity, noise, 10, torch.zeros((1, H, 1), dtype=torch.float64), np.zeros(H))
    assert torch.equal(out, euler(velocity, noise, 10))


@pytest.mark.parametrize("schedule", ["exp", "hard"])
def test_guided_chunk_is_consistent_with_the_executing_prefix(schedule):
    """The first d = 3 rows will execute as 1.5; the plan covers L = 5 rows. Unguided chunks ignore it (each
    draws its own latent); guided ones agree with it on the prefix and, through the shared latent, after it:
    the new chunk continues where the executing actions are, which is the point of RTC."""
    velocity = gaussian_flow()
    target = torch.full((1, H, 1), 1.5, dtype=torch.float64)
    guided_err, free_err = [], []
    for seed in range(10):
        noise = torch.randn((1, H, 1), generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
        guided = guided_sample(velocity, noise, 10, target, prefix_weights(3, 5, H, schedule))
        free = euler(velocity, noise, 10)
        guided_err.append(float((guided[0, :, 0] - 1.5).abs().max()))
        free_err.append(float((free[0, :, 0] - 1.5).abs().max()))
    assert np.mean(guided_err) < 0.15 and max(guided_err) < 0.3
    assert np.mean(free_err) > 1.0


def test_more_guidance_pulls_harder():
    velocity = gaussian_flow()
    noise = torch.randn((1, H, 1), generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    target = torch.full((1, H, 1), 1.5, dtype=torch.float64)
    w = prefix_weights(2, 4, H, "exp")
    errs = [float((guided_sample(velocity, noise, 10, target, w, g)[0, :2, 0] - 1.5).abs().max()) for g in (0.5, 5.0)]
    assert errs[1] < errs[0]


def test_inpaint_chunk_works_in_action_units():
    """A policy whose training actions have mean 0.5 and std 2 per dimension: the prefix is given in action
    units, the flow runs in normalised ones; the denormalised chunk follows the prefix."""
    velocity = gaussian_flow()
    noise = torch.randn((1, H, 7), generator=torch.Generator().manual_seed(4), dtype=torch.float64)
    mean, std = np.full(7, 0.5), np.full(7, 2.0)
    prefix = ActionPrefix(np.full((5, 7), 3.5), delay=3)  # 3.5 in action units = 1.5 normalised
    out = inpaint_chunk(velocity, noise, 10, prefix, mean, std)
    assert float((out[0] * 2.0 + 0.5 - 3.5).abs().max()) < 0.6
    free = inpaint_chunk(velocity, noise, 10, ActionPrefix(np.zeros((0, 7)), 3), mean, std)
    assert torch.equal(free, euler(velocity, noise, 10))


@pytest.mark.sim
def test_the_shipped_flow_policy_samples_under_rtc(spatial_env):
    """flow with a prefix: the executing rows follow the old plan; no prefix or an empty one is exactly the
    unguided chunk; the same prefix gives the same chunk (seeded noise)."""
    from lq_ros.policies import make_policy

    spatial_env.reset(0, seed=7)
    obs = spatial_env.observe(with_images=False)
    task = spatial_env.task
    policy = make_policy("flow")
    assert policy.supports_prefix
    # The old plans: the same policy's chunks from other noise (RTC's case: a plan the policy itself could
    # make; guidance cannot take a flow outside what it learned, so a far-fetched plan is not the test).
    arm, ratios = slice(0, 6), []
    for other_seed in (8, 9, 10, 11):
        policy.reset(task, seed=other_seed)
        plan = policy.infer(obs)[:6]
        policy.reset(task, seed=7)
        unguided = policy.infer(obs)
        assert np.array_equal(policy.infer(obs, prefix=ActionPrefix(np.zeros((0, 7)), 2)), unguided)
        guided = policy.infer(obs, prefix=ActionPrefix(plan, delay=2))
        assert np.array_equal(policy.infer(obs, prefix=ActionPrefix(plan, delay=2)), guided)
        ratios.append(np.abs(guided[:2, arm] - plan[:2, arm]).mean() / np.abs(unguided[:2, arm] - plan[:2, arm]).mean())
    # Guidance pulls every executing prefix towards its plan (measured: 0.62-0.71 of the unguided distance).
    assert max(ratios) < 0.85, ratios
