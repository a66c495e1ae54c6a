"""Comparing two sets of camera poses of the same views that differ by a similarity transform
(scale, rotation, translation), such as poses solved by COLMAP against reference poses."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Similarity(NamedTuple):
    """x -> scale * rotation @ x + translation."""

    scale: float
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * points @ self.rotation.T + self.translation


class PoseErrors(NamedTuple):
    """Per view, after aligning the first set of poses onto the second."""

    rotation_degrees: np.ndarray  # (N,) angle between the aligned and the reference orientation
    centre_error: np.ndarray  # (N,) distance between the aligned and the reference camera centre
    alignment: Similarity


def fit_similarity(source: np.ndarray, target: np.ndarray) -> Similarity:
    """The least-squares similarity taking points ``source`` (N, 3) onto ``target`` (N, 3),
    N >= 3 not collinear (Umeyama 1991: SVD of the cross-covariance, reflections excluded)."""
    mu_s, mu_t = source.mean(axis=0), target.mean(axis=0)
    src, dst = source - mu_s, target - mu_t
    u, sigma, vt = np.linalg.svd(dst.T @ src / len(source))
    sign = np.ones(3)
    sign[2] = np.sign(np.linalg.det(u @ vt))
    rotation = (u * sign) @ vt
    scale = float((sigma * sign).sum() / (src * src).sum(axis=1).mean())
    return Similarity(scale, rotation, mu_t - scale * rotation @ mu_s)


def pose_errors(c2w: np.ndarray, reference: np.ndarray) -> PoseErrors:
    """Errors of (N, 4, 4) camera-to-world poses against ``reference`` (same views, same axis
    convention) once the similarity fitted to the camera centres is applied to ``c2w``."""
    align = fit_similarity(c2w[:, :3, 3], reference[:, :3, 3])
    rotations = align.rotation @ c2w[:, :3, :3]
    relative = np.einsum("nji,njk->nik", reference[:, :3, :3], rotations)
    # atan2 of the angle's sine (from the antisymmetric part) and cosine (from the trace): arccos
    # alone loses small angles to rounding.
    skew = relative - relative.transpose(0, 2, 1)
    sin = np.linalg.norm(np.stack([skew[:, 2, 1], skew[:, 0, 2], skew[:, 1, 0]], -1), axis=-1) / 2.0
    cos = (np.trace(relative, axis1=1, axis2=2) - 1.0) / 2.0
    centres = align.apply(c2w[:, :3, 3])
    return PoseErrors(
        np.degrees(np.arctan2(sin, cos)), np.linalg.norm(centres - reference[:, :3, 3], axis=1), align
    )
