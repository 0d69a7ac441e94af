"""Video sequences for the tracking-on-real-video study: the frames of one scene with every object's truth and box.

Real YCB-Video dev videos and rendered video alike are BOP folders; an object's sequence is its frames with
``visib_fract >= min_visib`` (``benchmarks.tracking.load_sequences``). A *video* here is one scene: its sequences
tracked together, as a robot's tracker would, over its first ``max_frames`` frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from benchmarks.tracking import Sequence, load_sequences
from refiner_rt.pretrained import pretrained_models

SHIPPED = tuple(sorted(m.object_id for m in pretrained_models()))


@dataclass
class Video:
    """One scene: its consecutive frame ids, the images (BGR) and the sequences of its objects."""

    dataset: str
    scene: str
    frames: list[int]
    images: dict[int, np.ndarray]
    seqs: list[Sequence]

    @property
    def K(self) -> np.ndarray:
        return self.seqs[0].K

    @property
    def name(self) -> str:
        return f"{self.dataset}/{self.scene}"


def dataset_name(data: Path) -> str:
    """A BOP folder as the records name it: ``real_ycbv_dev/test`` for a split folder, else the folder's name."""
    data = Path(data).resolve()
    return f"{data.parent.name}/{data.name}" if data.name in ("test", "val", "train") else data.name


def load_videos(data: Path, scenes: list[str] | None = None, max_frames: int = 100, min_visib: float = 0.3,
                min_frames: int = 10) -> list[Video]:
    """The videos of ``data`` (a BOP split folder), each cut to its first ``max_frames`` consecutive frames."""
    seqs, _ = load_sequences(Path(data), set(SHIPPED), min_visib, 1)
    by_scene: dict[str, list[Sequence]] = {}
    for s in seqs:
        if scenes is None or s.scene in scenes:
            by_scene.setdefault(s.scene, []).append(s)
    videos = []
    for scene, group in sorted(by_scene.items()):
        first = min(min(s.images) for s in group)
        frames = list(range(first, first + max_frames))
        any_path = Path(next(iter(group[0].images.values())))
        images = {}
        for f in frames:
            im = cv2.imread(str(any_path.with_name(f"{f:06d}{any_path.suffix}")), cv2.IMREAD_COLOR)
            if im is None:
                break
            images[f] = im
        frames = [f for f in frames if f in images]
        kept = []
        for s in group:
            for table in (s.q_gt, s.boxes, s.images):
                for f in [f for f in table if f not in images]:
                    del table[f]
            if len(s.images) >= min_frames:
                kept.append(s)
        if kept:
            videos.append(Video(Path(data).resolve().parent.name if Path(data).name == "test" else Path(data).name,
                                scene, frames, images, kept))
    return videos
