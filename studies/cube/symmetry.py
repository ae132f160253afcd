r"""The cube study's LCS in a body frame chosen by the cube's symmetry: the contact LCS of
:mod:`studies.cube.kinematic` stepped in the frame whose ``+z`` face points most upwards.

A cube with isotropic inertia is unchanged by the 24 rotations that map it onto itself (signed
permutation matrices ``S`` with ``det S = 1``): re-labelling the body axes by ``S`` (body
coordinates ``r -> S r``) maps every motion onto a motion. In the re-labelled frame the state is

    q_S = q ⊗ s^{-1},   p_S = p,   w_S = S w,   v_S = v,   g_S = S g,

with ``s`` the unit quaternion of ``S`` and ``g = R(q)^T e_z`` the up direction in the body frame.
Of the 24, :data:`FRAMES` keeps one per face (the one nearest the identity that takes the face to
``+z``), and :func:`frame_of` picks, for each state, the face with the largest up component
``argmax_S (S g)_z``. In that frame the lowest face is always ``-z`` and ``g`` stays within
``(S g)_z >= |(S g)_x|, |(S g)_y|``: the torque arms ``r_c × g`` of the corners that touch the floor
vary over that cap only, instead of over the whole sphere, where a corner's arm changes with
which of its three faces is down; so the constant ``C`` of one LCS describes them far better, and
the frame boundaries ``|g_z| = |g_x|`` are where a tipping cube passes over an edge.

- :func:`frame_of`, :func:`to_frame`, :func:`from_frame`: the frame of a state and the two maps;
- :func:`segments`: tosses cut where the frame changes, each piece in its frame (a trajectory of
  the cube in one frame, for :func:`lcs_cvx.fit`); every transition is kept, in the frame of its
  first state;
- :func:`symmetric_lcs`: :func:`studies.cube.kinematic.contact_lcs` with the complementarity rows
  blind to the quaternion and the horizontal position (``D``'s columns 0..5 held at 0): the floor
  is the same everywhere, and the contacts see the orientation through the up coordinates only
  (a quaternion and its negative are one orientation); it starts with ``C = 0``, at free flight
  (with random ``C`` the starting model's units kick the velocities at random, and a fit with 16
  units from 8 tosses found no iterate whose held-out rollouts stayed bounded);
- :func:`prepare`: what it is fitted on, the :func:`segments` with the up coordinates;
- :func:`stepper`: a model's step in the frame of each state, mapped back.
"""

from __future__ import annotations

import itertools
import math

import torch
from scipy.spatial.transform import Rotation

import lcs_cvx
from lcs_cvx.kinematics import quaternion_product, up_in_body

from . import kinematic

__all__ = ["FRAMES", "frame_of", "to_frame", "from_frame", "segments", "symmetric_lcs", "prepare", "stepper"]

_CONJUGATE = torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=torch.float64)


def _rotations() -> list[torch.Tensor]:
    """The 24 proper rotations of the cube: signed permutation matrices with determinant 1."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            S = torch.zeros(3, 3, dtype=torch.float64)
            S[range(3), perm] = torch.tensor(signs, dtype=torch.float64)
            if torch.linalg.det(S) > 0:
                out.append(S)
    return out


def _quaternion(S: torch.Tensor) -> torch.Tensor:
    """The unit quaternion ``(w, x, y, z)`` of the rotation matrix ``S``, ``w >= 0``."""
    x, y, z, w = Rotation.from_matrix(S.numpy()).as_quat()
    q = torch.tensor([w, x, y, z], dtype=torch.float64)
    return q if q[0] >= 0 else -q


def _frames() -> torch.Tensor:
    best: dict[tuple[float, ...], torch.Tensor] = {}
    for S in _rotations():
        face = tuple(S[2].tolist())  # the body direction S takes to +z
        if face not in best or torch.trace(S) > torch.trace(best[face]):
            best[face] = S
    return torch.stack([best[f] for f in sorted(best, reverse=True)])


#: ``(6, 3, 3)``: one rotation per face of the cube, taking that face to ``+z``.
FRAMES = _frames()
_QUATERNIONS = torch.stack([_quaternion(S) for S in FRAMES])


def frame_of(x: torch.Tensor) -> torch.Tensor:
    """``(N,)`` int64: the index in :data:`FRAMES` of the frame of each state ``x`` ``(N, >=4)``
    (quaternion first): the face with the largest up component."""
    g = up_in_body(x[:, :4].to(torch.float64))
    return torch.argmax(g @ FRAMES[:, 2].T, dim=1)


def to_frame(x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """The 13-states ``x`` ``(N, 13)`` (:data:`lcs_cvx.datasets.CUBE_COLUMNS`) in the frames ``k``
    ``(N,)``: ``q ⊗ s^{-1}``, ``p``, ``S w``, ``v``."""
    q = quaternion_product(x[:, :4], _QUATERNIONS[k] * _CONJUGATE)
    w = torch.einsum("nij,nj->ni", FRAMES[k], x[:, 7:10])
    return torch.cat([q, x[:, 4:7], w, x[:, 10:13]], dim=1)


def from_frame(x: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """The inverse of :func:`to_frame`: ``q_S ⊗ s``, ``p``, ``S^T w_S``, ``v``."""
    q = quaternion_product(x[:, :4], _QUATERNIONS[k])
    w = torch.einsum("nji,nj->ni", FRAMES[k], x[:, 7:10])
    return torch.cat([q, x[:, 4:7], w, x[:, 10:13]], dim=1)


def segments(tosses: lcs_cvx.Trajectories) -> lcs_cvx.Trajectories:
    """The tosses cut where :func:`frame_of` changes: a piece runs from the first state in a frame
    to the first state of the next frame (that state in the piece's frame), so every transition
    appears once, in the frame of its first state."""
    xs: list[torch.Tensor] = []
    for x in tosses.xs:
        k = frame_of(x)
        cuts = [0, *(torch.nonzero(k[1:] != k[:-1]).flatten() + 1).tolist(), x.shape[0] - 1]
        for a, b in zip(cuts[:-1], cuts[1:], strict=True):
            if b > a:
                xs.append(to_frame(x[a:b + 1], k[a].expand(b + 1 - a)))
    return lcs_cvx.Trajectories(xs, [x.new_zeros(len(x) - 1, 0) for x in xs])


def symmetric_lcs(n_lam: int, seed: int = 0) -> lcs_cvx.LCS:
    """:func:`studies.cube.kinematic.contact_lcs` with ``D[:, 0:6]`` (quaternion, ``p_x``, ``p_y``)
    held at 0, starting at ``C = 0`` (free flight)."""
    model = kinematic.contact_lcs(n_lam, seed=seed)
    D = torch.full((n_lam, model.n_x), math.nan, dtype=torch.float64)
    D[:, 0:6] = 0.0
    model.hold(D=D)
    with torch.no_grad():
        model.C.zero_()
    return model


def prepare(tosses: lcs_cvx.Trajectories) -> lcs_cvx.Trajectories:
    """The :func:`segments` of the tosses with the up coordinates appended
    (:func:`studies.cube.kinematic.augment`)."""
    return kinematic.augment(segments(tosses))


def stepper(model: lcs_cvx.LCS):  # noqa: ANN201 - a studies.cube.metrics.Stepper
    """``x (N, 13) -> x'``: ``model``'s step (:func:`studies.cube.kinematic.stepper`) in the frame
    of each state, mapped back."""
    inner = kinematic.stepper(model)

    def step(x: torch.Tensor) -> torch.Tensor:
        k = frame_of(x)
        return from_frame(inner(to_frame(x, k)), k)
    return step
