"""How many rays a training step draws so that the field's work stays near a sample budget."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class SampleBudget:
    """Rays per step that hold a step's field evaluations near ``target`` samples: as skipping
    leaves fewer samples per ray, the batch grows, up to ``max_rays`` (nerfacc's recipe).

    Attributes:
        target: samples per step the batch size aims at.
        max_rays: the largest batch.
        dense_samples_per_ray: samples per ray assumed before anything is known (a grid starts
            fully occupied), for the first batch.
    """

    target: int
    max_rays: int = 1 << 18
    dense_samples_per_ray: int = 256

    def __post_init__(self) -> None:
        for name in ("target", "max_rays", "dense_samples_per_ray"):
            if not getattr(self, name) >= 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")

    def first_rays(self, batch_rays: int) -> int:
        """The first batch: ``batch_rays`` or fewer, as if every ray were dense."""
        return min(batch_rays, max(1, self.target // self.dense_samples_per_ray))

    def next_rays(self, num_rays: int, num_samples: int) -> int:
        """The next batch, given that ``num_rays`` rays just gave ``num_samples`` samples."""
        rays = num_rays * self.target / max(num_samples, 1)
        return int(min(max(rays, 1), self.max_rays))
