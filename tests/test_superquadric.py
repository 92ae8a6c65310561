"""Superquadric geometry against closed forms, meshes and Monte Carlo."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from sgjax.geometry.rotations import random_rotation, so3_exp
from sgjax.geometry.superquadric import (
    Superquadric,
    canonicalize,
    dual,
    equivalent_parameterisations,
    implicit_function,
    radial_distance,
    relative_scale_error,
    sample_surface,
    tangent_radial_distance_local,
    to_local,
    to_mesh,
    volume,
)

shapes = st.tuples(
    st.tuples(*[st.floats(0.01, 0.12)] * 3),
    st.tuples(st.floats(0.1, 2.0), st.floats(0.1, 2.0)),
    st.integers(0, 2**31 - 1),
)


def make(scale, eps, seed):
    key = jax.random.key(seed)
    return Superquadric.create(scale, eps, random_rotation(key), jax.random.uniform(key, (3,), minval=-0.5, maxval=0.5))


@settings(max_examples=25, deadline=None)
@given(shapes)
def test_surface_samples_lie_on_the_surface(shape):
    sq = make(*shape)
    pts, normals = sample_surface(sq, 500, seed=1)
    # samples lie on mesh triangles: within the mesh's chord error (well under 1 % of the size)
    d = np.asarray(radial_distance(jnp.asarray(pts), sq))
    assert np.all(d < 0.005 * max(shape[0]))
    assert np.median(d) < 0.001 * max(shape[0])
    # outward normals: the centre lies behind every tangent plane of a convex surface
    assert np.all(np.sum(normals * (pts - np.asarray(sq.translation)), -1) > -1e-9)


@settings(max_examples=15, deadline=None)
@given(shapes)
def test_closed_form_volume_matches_mesh_volume(shape):
    sq = make(*shape)
    mesh = to_mesh(sq)
    assert mesh.is_watertight
    assert float(volume(sq)) == pytest.approx(mesh.volume, rel=5e-3)


def test_volume_special_cases():
    assert float(volume(Superquadric.create([1.0, 1.0, 1.0], [1.0, 1.0]))) == pytest.approx(4 / 3 * np.pi, rel=1e-5)
    # eps -> 0 tends to the box 2a x 2b x 2c
    assert float(volume(Superquadric.create([1.0, 2.0, 3.0], [0.1, 0.1]))) == pytest.approx(48.0, rel=0.03)


def test_inside_outside_and_radial_distance_along_rays():
    sq = Superquadric.create([0.05, 0.03, 0.08], [0.7, 1.3])
    pts, _ = sample_surface(sq, 200, seed=3)
    # move the samples exactly onto the surface along their rays: F is homogeneous of degree 2/eps1
    pts = pts * np.asarray(implicit_function(jnp.asarray(pts), sq))[:, None] ** (-0.7 / 2)
    np.testing.assert_allclose(implicit_function(jnp.asarray(pts), sq), 1.0, rtol=1e-4)
    for k in (0.5, 1.5):
        f = np.asarray(implicit_function(jnp.asarray(pts * k), sq))
        assert np.all(f < 1) if k < 1 else np.all(f > 1)
        d = np.asarray(radial_distance(jnp.asarray(pts * k), sq))
        np.testing.assert_allclose(d, np.abs(k - 1) * np.linalg.norm(pts, axis=-1), rtol=1e-4, atol=1e-7)


def test_tangent_distance_is_the_euclidean_distance_near_the_surface():
    sq = Superquadric.create([0.05, 0.03, 0.08], [0.4, 1.6])
    pts, normals = sample_surface(sq, 1000, seed=2)
    offset = np.random.default_rng(0).normal(0.0, 0.002, (1000, 1))
    d = np.asarray(tangent_radial_distance_local(jnp.asarray(pts + offset * normals), sq.scale, sq.epsilon))
    assert np.median(np.abs(d - offset[:, 0])) < 1e-4


@settings(max_examples=30, deadline=None)
@given(shapes)
def test_canonical_frame_describes_the_same_surface(shape):
    eps = shape[1]
    assume(eps[0] == eps[1] or abs(eps[0] - eps[1]) > 1e-3)  # within the tolerance the permutation is approximate
    sq = make(*shape)
    can = canonicalize(sq)
    pts, _ = sample_surface(sq, 300, seed=0)
    np.testing.assert_allclose(radial_distance(jnp.asarray(pts), can), radial_distance(jnp.asarray(pts), sq), atol=1e-6)
    r = np.asarray(can.rotation)
    np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-5)
    assert np.linalg.det(r) == pytest.approx(1.0, abs=1e-5)
    assert can.scale[0] >= can.scale[1]
    assert r[2, 2] >= 0


@settings(max_examples=30, deadline=None)
@given(shapes, st.integers(0, 7), st.integers(0, 3))
def test_canonical_form_is_the_same_for_every_equivalent_frame(shape, flips, turns):
    """Axis sign flips (in pairs) and quarter turns about z give the same canonical superquadric."""
    sq = make(*shape)
    signs = np.array([1 - 2 * ((flips >> i) & 1) for i in range(2)] + [1.0])
    signs[2] = signs[0] * signs[1]
    rot = np.asarray(sq.rotation) * signs
    scale = np.asarray(sq.scale)
    for _ in range(turns):  # 90 deg about z: x' = y, y' = -x
        rot = np.stack([rot[:, 1], -rot[:, 0], rot[:, 2]], -1)
        scale = scale[[1, 0, 2]]
    other = Superquadric.create(scale, sq.epsilon, rot, sq.translation)
    a, b = canonicalize(sq), canonicalize(other)
    if abs(shape[0][0] - shape[0][1]) < 1e-3 or abs(np.asarray(sq.rotation)[2, 2]) < 1e-3:
        return  # ties: both frames are canonical
    np.testing.assert_allclose(a.scale, b.scale, rtol=1e-6)
    np.testing.assert_allclose(a.rotation, b.rotation, atol=1e-5)


def test_equivalent_parameterisation_of_a_square_prism_is_its_diamond_dual():
    sq = Superquadric.create([0.04, 0.04, 0.06], [0.2, 0.1], so3_exp(jnp.array([0.3, -0.2, 0.5])), [0.1, 0, 0])
    both, applies = equivalent_parameterisations(sq)
    assert bool(applies)
    eq = both[1]
    assert float(eq.epsilon[1]) == pytest.approx(1.9)
    assert float(eq.scale[0]) > float(sq.scale[0]) * 1.3  # diamond vertices reach the square's corners
    # the dual describes nearly the same surface: surface points of one are close to the other
    pts, _ = sample_surface(sq, 500, seed=0)
    d = np.asarray(radial_distance(jnp.asarray(pts), eq))
    assert np.median(d) < 0.003
    # and the rule does not fire for a cylinder-like cross-section or unequal in-plane axes
    assert not bool(equivalent_parameterisations(Superquadric.create([0.04, 0.04, 0.06], [0.2, 1.0]))[1])
    assert not bool(equivalent_parameterisations(Superquadric.create([0.04, 0.02, 0.06], [0.2, 0.1]))[1])
    np.testing.assert_allclose(both[0].scale, sq.scale)


def test_dual_is_an_involution():
    sq = Superquadric.create([0.04, 0.04, 0.06], [0.5, 0.15], so3_exp(jnp.array([0.3, -0.2, 0.5])), [0.0, 0.1, 0])
    back = dual(dual(sq))
    np.testing.assert_allclose(back.scale, sq.scale, rtol=1e-5)
    np.testing.assert_allclose(back.epsilon, sq.epsilon, rtol=1e-5)
    pts, _ = sample_surface(sq, 200, seed=0)
    np.testing.assert_allclose(to_local(jnp.asarray(pts), back)[:, 2], to_local(jnp.asarray(pts), sq)[:, 2], atol=1e-6)


def test_relative_scale_error_ignores_the_frame_choice():
    sq = make((0.05, 0.03, 0.08), (0.5, 1.0), 4)
    rot = np.asarray(sq.rotation)
    swapped = Superquadric.create(np.asarray(sq.scale)[[1, 0, 2]], sq.epsilon, np.stack([rot[:, 1], -rot[:, 0], rot[:, 2]], -1), sq.translation)
    assert relative_scale_error(swapped, sq) < 1e-6
    bigger = Superquadric.create(np.asarray(sq.scale) * 1.1, sq.epsilon, sq.rotation, sq.translation)
    assert relative_scale_error(bigger, sq) == pytest.approx(0.1, rel=1e-4)
