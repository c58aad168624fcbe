"""The anchored map (modal derivatives + an MLP stripped of its Taylor polynomial at z = 0) and its fit option."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from redsim import metrics, scenes
from redsim.baselines import modal_analysis, modal_derivatives
from redsim.cubature import AffineOutput, CubatureConfig, CubatureEnergy, build_cubature
from redsim.runtime import LatentStepper
from redsim.subspace import AnchoredSubspace, QuadraticSubspace, SubspaceConfig, load_subspace
from redsim.subspace.anchored import hidden_jet
from redsim.trainers import FitConfig, fit_subspace
from redsim.trainers.anchored import anchor_polynomial
from redsim.trainers.fit import fit_command


def _random_map(
    act: str = "elu",
    *,
    order: int = 2,
    condition_dim: int = 0,
    anchor: bool = False,
    radius: float = 0.0,
    seed: int = 0,
):
    """An anchored map with random weights (output weights not scaled down) and a random polynomial, float64."""
    generator = torch.Generator().manual_seed(seed)
    n, d = 7, 3
    poly = QuadraticSubspace(
        *(torch.randn(*shape, generator=generator, dtype=torch.float64) for shape in ((n, d), (n,), (n, 6)))
    )
    config = SubspaceConfig(
        latent_dim=d, output_dim=n, condition_dim=condition_dim, hidden_width=16, hidden_layers=3, activation=act
    )
    cond = torch.randn(condition_dim, generator=generator, dtype=torch.float64) if anchor else None
    torch.manual_seed(seed)
    return AnchoredSubspace(config, poly, order, cond, radius).double(), poly


@pytest.mark.parametrize("act", ["elu", "tanh", "silu"])
def test_the_jet_is_the_hidden_layers_value_jacobian_and_hessian(act: str) -> None:
    f, _ = _random_map(act, condition_dim=2)
    cond = torch.randn(2, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    value, jac, hess = hidden_jet(f.net, cond)
    origin = torch.zeros(3, dtype=torch.float64)
    for k in range(2):
        hidden = lambda z, k=k: f.hidden(z[None], cond[k : k + 1])[0]  # noqa: E731
        torch.testing.assert_close(value[k], hidden(origin))
        torch.testing.assert_close(jac[k], torch.autograd.functional.jacobian(hidden, origin))
        for unit in (0, 5):
            want = torch.autograd.functional.hessian(lambda z, u=unit, h=hidden: h(z)[u], origin)
            torch.testing.assert_close(hess[k, unit], want)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("case", ["plain", "each", "default", "taper"])
def test_the_map_is_the_polynomial_to_its_order_at_z0(order: int, case: str) -> None:
    """|f(e u) - P(e u)| shrinks as e^(order + 1) (finite differences): halving e divides it by ~2^(order + 1).

    For a conditional map this holds at every condition with the Taylor polynomial taken per condition ("each"),
    and only at the anchor condition with "default" (elsewhere f(0, c) moves with c); the taper of a radius keeps
    it. tanh, because an ELU's
    second derivative jumps where a unit's input crosses 0, so the e^3 rate needs e below the nearest crossing.
    """
    conditional = case in ("each", "default")
    radius = 0.5 if case == "taper" else 0.0
    f, poly = _random_map("tanh", order=order, condition_dim=2 * conditional, anchor=case == "default", radius=radius)
    generator = torch.Generator().manual_seed(1)
    u = torch.randn(5, 3, generator=generator, dtype=torch.float64)
    cond = None
    if conditional:
        cond = f.anchor_cond.expand(5, -1) if case == "default" else torch.randn(5, 2, generator=generator).double()
    base = poly(u) if order == 2 else poly.affine(u, None)
    target = poly if order == 2 else (lambda z: poly.affine(z, None))
    with torch.no_grad():
        gaps = [float((f(e * u, cond) - target(e * u)).norm()) for e in (2e-3, 1e-3)]
    assert gaps[0] / gaps[1] == pytest.approx(2 ** (order + 1), rel=0.1), gaps
    assert gaps[0] < 1e-2 * float((base - poly.offset).norm())
    if case == "default":
        other = torch.randn(1, 2, generator=generator, dtype=torch.float64)
        with torch.no_grad():
            assert float((f(torch.zeros(1, 3, dtype=torch.float64), other) - poly.offset).norm()) > 1e-3


def test_save_load_round_trip_and_the_affine_output(tmp_path) -> None:
    f, _ = _random_map(condition_dim=2, anchor=True, radius=0.7)
    f.metadata["scene"] = "toy"
    f.save(tmp_path / "anchored")
    g = load_subspace(tmp_path / "anchored.pt")
    assert isinstance(g, AnchoredSubspace) and g.metadata["kind"] == "anchored" and (g.order, g.radius) == (2, 0.7)
    z = torch.randn(4, 3, dtype=torch.float64)
    c = torch.randn(4, 2, dtype=torch.float64)
    torch.testing.assert_close(g(z, c), f(z, c))
    output = AffineOutput(f)
    assert output.feature_dim == 16 + 3 + 6
    torch.testing.assert_close(output(z, c), f(z, c))


def test_fit_option_trains_a_map_that_holds_modal_derivatives_and_runs_in_the_runtime(tmp_path) -> None:
    """A 40-step anchored fit of the tiny bar: f(0) is the rest state, df/dz(0) sigma times the lowest modes and
    d2f/dz2(0) the modal derivatives (central differences, float64); the checkpoint loads, the runtime and an
    all-element cubature step on it stay finite."""
    scene = scenes.build("toy_tiny_bar_2d")
    sigma = 0.05
    result = fit_subspace(
        scene, dim=2, sigma=sigma, lam=10.0, steps=40, anchor_map="md", out=tmp_path / "bar", progress=False
    )
    assert all(torch.isfinite(torch.tensor(h["loss"])) for h in result.history)
    assert "--anchor-map md" in result.subspace.metadata["command"]
    f = load_subspace(tmp_path / "bar.pt", scene=scene)
    assert isinstance(f, AnchoredSubspace)
    f = f.double()
    rest, _ = metrics.rest_state(scene)
    want = modal_derivatives(scene, 2, sigma=sigma, rest=rest)
    step = 1e-3
    eye = step * torch.eye(2, dtype=torch.float64)
    at = lambda z: f(z[None])[0]  # noqa: E731
    origin = torch.zeros(2, dtype=torch.float64)
    torch.testing.assert_close(at(origin), rest.float().double(), atol=1e-12, rtol=0)  # the fit ran in float32
    jac = torch.stack([(at(e) - at(-e)) / (2 * step) for e in eye], 1)
    torch.testing.assert_close(jac, want.basis, atol=1e-6 * float(want.basis.abs().max()), rtol=0)
    second = (at(eye[0] + eye[1]) - at(eye[0] - eye[1]) - at(eye[1] - eye[0]) + at(-eye[0] - eye[1])) / (4 * step**2)
    torch.testing.assert_close(second, want.quadratic[:, 1], atol=1e-4 * float(want.quadratic.abs().max()), rtol=0)
    z = 0.3 * torch.ones(2, 2)
    loads = torch.zeros(2, len(scene.handles), scene.dim)
    f = f.float()
    cubature = build_cubature(scene, f, CubatureConfig(elements=1000, samples=32, episodes=0))
    for energy in (None, CubatureEnergy(scene, f, cubature)):
        stepper = LatentStepper(scene, f, 0.02, energy=energy)
        z_next, stats = stepper.step(z, z, loads)
        assert bool(torch.isfinite(z_next).all()) and not bool(stats.diverged.any())


def test_modes_anchor_is_linear_modes_and_bad_settings_are_refused() -> None:
    scene = scenes.build("toy_tiny_bar_2d")
    poly = anchor_polynomial(scene, 2, 0.05, "modes")
    rest, _ = metrics.rest_state(scene)
    torch.testing.assert_close(poly.basis, modal_analysis(scene, 2, sigma=0.05, rest=rest).basis)
    assert float(poly.quadratic.abs().max()) == 0.0
    for bad in ({"anchor_map": "pca"}, {"anchor_map": "md", "modal": 1.0}, {"anchor_map": "md", "seed_bias": True}):
        with pytest.raises(ValueError, match="anchor_map"):
            FitConfig(**bad)
    with pytest.raises(ValueError, match="anchor_map"):
        FitConfig(latent_dim=1, periodic=(0,), anchor_map="md")
    with pytest.raises(ValueError, match="anchor_map_cond"):
        FitConfig(anchor_map_cond="all")
    # options of the anchored map without it would do nothing (and leave the recorded command)
    with pytest.raises(ValueError, match=r"anchor_map_cond must be .*'default' without anchor_map"):
        FitConfig(anchor_map_cond="each")
    with pytest.raises(ValueError, match=r"anchor_radius must be .*0 without anchor_map"):
        FitConfig(anchor_radius=1.5)
    FitConfig(anchor_map="md", anchor_map_cond="each", anchor_radius=1.5)
    config = FitConfig(latent_dim=2, anchor_map="modes")
    assert "--anchor-map modes" in fit_command(scene, config, 0, None)
    assert "--anchor-map" not in fit_command(scene, dataclasses.replace(config, anchor_map="none"), 0, None)
    with pytest.raises(ValueError, match="periodic"):
        AnchoredSubspace(SubspaceConfig(latent_dim=2, output_dim=7, periodic=(0,)), _random_map()[1])


@pytest.mark.parametrize("where", ["each", "default"])
def test_conditional_fit_anchors_the_default_condition(where: str) -> None:
    """A 3-step conditional fit: at the default condition f(0, c0) is the rest state either way; at another
    condition it is too with "each" (the Taylor polynomial is taken per condition), not with "default"."""
    scene = scenes.build("conditional_bar", cells_x=6, cells_y=2)
    result = fit_subspace(
        scene,
        dim=2,
        sigma=0.05,
        lam=10.0,
        steps=3,
        conditional=True,
        anchor_map="md",
        anchor_map_cond=where,
        progress=False,
    )
    f = result.subspace.double()
    assert f"--anchor-map md --anchor-map-cond {where}" in f.metadata["command"]
    rest, _ = metrics.rest_state(scene)
    space = scene.condition_space
    origin = torch.zeros(1, 2, dtype=torch.float64)
    torch.testing.assert_close(
        f(origin, space.default[None].float().double())[0], rest.float().double(), atol=1e-12, rtol=0
    )
    with torch.no_grad():
        other = f(origin, torch.stack([space.low, space.high], 1).mean(1)[None].double() + 0.1)[0]
    assert (float((other - rest.float().double()).abs().max()) < 1e-12) == (where == "each")


def test_the_kept_jet_follows_weight_updates_and_casts() -> None:
    """A map in use keeps its jet at z = 0; an in-place weight update or a cast must not reuse a stale one."""
    f, _ = _random_map(radius=0.0)
    f.requires_grad_(False)
    z = torch.randn(3, 3, dtype=torch.float64)
    before = f(z)
    with torch.no_grad():
        f.net.mlp[0].weight.mul_(1.5)
    fresh, _ = _random_map(radius=0.0)
    with torch.no_grad():
        fresh.net.mlp[0].weight.mul_(1.5)
    torch.testing.assert_close(f(z), fresh(z))
    assert not torch.allclose(f(z), before)
    torch.testing.assert_close(f.float()(z.float()), fresh.float()(z.float()))
