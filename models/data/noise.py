"""Coarse-pose noise specifications (``uniform:0:30``, ``normal:10:5``, ``twist:0:30``) for training and evaluation.

The paper (section "Training Data") perturbs the ground truth with a rotation about a uniform random
axis by an angle from ``U(0, 30)`` degrees (baseline), ``N(30, 5)`` or ``N(10, 5)``:
``q_in = q_gt * q_noise`` and the label is ``q_noise^-1``, so that ``q_in * q_label = q_gt``.
``twist:LOW:HIGH`` turns about the object frame's z axis only (``q_noise`` multiplies ``q_gt`` on the right, so it
acts in the object's frame) by an angle from ``U(LOW, HIGH)`` with a random sign: a first training stage that
teaches a refiner the turn of an object about its own axis (the master chef can's z axis in the YCB scan frame,
``benchmarks/studies/can_twist``). Quaternions are ``wxyz``; angles in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from refiner_rt import quaternion as rq

__all__ = ["NoiseSpec", "perturb", "TWIST_AXIS"]

TWIST_AXIS = (0.0, 0.0, 1.0)  # the object-frame axis of ``twist`` noise


@dataclass(frozen=True)
class NoiseSpec:
    """An angle distribution for coarse-pose noise: ``uniform`` (low, high) or ``normal`` (mean, std) about uniform
    random axes, or ``twist`` (low, high) about :data:`TWIST_AXIS` with a random sign; degrees."""

    distribution: str
    a: float
    b: float

    @classmethod
    def parse(cls, text: str) -> "NoiseSpec":
        """Parse ``"uniform:LOW:HIGH"``, ``"normal:MEAN:STD"`` or ``"twist:LOW:HIGH"`` (degrees).

        Raises:
            ValueError: anything else, with the expected form.
        """
        parts = str(text).split(":")
        try:
            if len(parts) != 3:
                raise ValueError
            dist, a, b = parts[0].strip().lower(), float(parts[1]), float(parts[2])
        except ValueError:
            raise ValueError(f"noise must look like 'uniform:0:30', 'normal:10:5' or 'twist:0:30' (degrees); got "
                             f"{text!r}") from None
        spec = cls(dist, a, b)
        spec.sample(0, np.random.default_rng(0))  # validates distribution and parameters
        return spec

    def sample(self, n: int, rng: np.random.Generator) -> np.ndarray:
        """``(n, 4)`` float64 ``wxyz`` noise rotations (paper's uniform-axis sampling, or turns about
        :data:`TWIST_AXIS`)."""
        if self.distribution == "twist":
            if not 0.0 <= self.a <= self.b <= 180.0:
                raise ValueError(f"twist noise needs 0 <= LOW <= HIGH <= 180 degrees; got {self.a:g}, {self.b:g}")
            angle = np.radians(rng.uniform(self.a, self.b, n) * rng.choice([-1.0, 1.0], n))
            return np.column_stack([np.cos(angle / 2), np.outer(np.sin(angle / 2), TWIST_AXIS)])
        return rq.sample_rotation_noise(n, self.distribution, self.a, self.b, rng)

    def __str__(self) -> str:
        return f"{self.distribution}:{self.a:g}:{self.b:g}"


def perturb(q_gt: np.ndarray, noise: NoiseSpec, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Coarse inputs and labels for ground-truth rotations.

    Args:
        q_gt: ``(N, 4)`` ground-truth rotations, ``wxyz`` (in the network's rotation frame).
        noise: the angle distribution.
        rng: random generator.

    Returns:
        ``(q_in, q_label)``: ``(N, 4)`` float64 ``wxyz``; ``q_in = q_gt * q_noise`` and
        ``q_label = q_noise^-1`` (so ``q_in * q_label = q_gt``).
    """
    q_noise = noise.sample(len(q_gt), rng)
    return rq.normalize(rq.multiply(q_gt, q_noise)), rq.inverse(q_noise)
