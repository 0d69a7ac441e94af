"""A crop cache: every sample's network-input crop, cut once by the shared crop rule and stored as a uint8 memmap.

Training reads tens of thousands of ``S x S`` crops per epoch; decoding a 640x480 PNG per crop
would dominate the step time on a CPU. :class:`CropCache` cuts each sample's crop once with
:func:`refiner_rt.preprocess.crop_to_square` (the rule the runtime uses, docs/design.md §3)
and stores it in ``<cache_dir>``::

    crops.npy       (N, S, S, 3) uint8, BGR, opened as a read-only memmap (numpy .npy format)
    masks.npy       (N, S, S) uint8, 1 on the instance's visible pixels, cut by the same rule;
                    only when some sample has a mask (``Sample.mask_path``)
    index.npz       per crop: q_gt (N, 4) float64 wxyz object to camera, R (N, 3, 3), t (N, 3)
                    metres, K (N, 3, 3), box_xyxy (N, 4) pixels, obj_id, scene_id, frame_id,
                    image_path, visib_fract (NaN when unknown), has_mask (bool)
    manifest.json   what the cache was built from: a fingerprint of the sample list (paths, ids,
                    poses, boxes, K, in order), S, context, the source images' sizes and mtimes,
                    the crop rule's code version and the OpenCV version; written last

``build_or_load`` rebuilds whenever any of these differs, and reuses the cache otherwise. Crop
``i`` belongs to ``samples[i]`` (input order is kept). Each image is decoded once however many
samples it holds. Concurrent builders of one ``cache_dir`` (e.g. DDP ranks) serialise on a file
lock, so one builds and the others load.
"""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import json
import logging
import os
import time
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from models.data.sample import Sample
from refiner_rt import preprocess
from refiner_rt import quaternion as rq

__all__ = ["CropCache", "CACHE_FORMAT", "crop_rule_version", "samples_fingerprint"]

log = logging.getLogger(__name__)

CACHE_FORMAT = "refiner-rt/crops/1"
_CROPS, _MASKS, _INDEX, _MANIFEST, _LOCK = "crops.npy", "masks.npy", "index.npz", "manifest.json", ".lock"
# Manifest keys that must match for a cache to be reused.
_KEYS = ("format", "n", "size", "context", "crop_filter", "samples_fingerprint", "sources_fingerprint",
         "crop_rule_version")
_IMAGES_PER_TASK = 16


def crop_rule_version() -> str:
    """Hash of the crop rule's code (``crop_window``, ``crop_matrix``, ``crop_to_square``) and the OpenCV version."""
    h = hashlib.sha256()
    for fn in (preprocess.crop_window, preprocess.crop_matrix, preprocess.crop_to_square):
        h.update(inspect.getsource(fn).encode())
    h.update(cv2.__version__.encode())
    return h.hexdigest()[:16]


def samples_fingerprint(samples: Sequence[Sample]) -> str:
    """SHA-256 of the ordered sample list: image path, object, scene, frame, instance, box, R, t, K, mask."""
    h = hashlib.sha256()
    for s in samples:
        h.update(f"{s.image_path}\0{s.obj_id}\0{s.scene_id}\0{s.frame_id}\0{s.instance}\0".encode())
        if s.mask_path:  # samples without a mask hash as before masks existed, so their caches stay valid
            h.update(f"mask\0{s.mask_path}\0{s.mask_value}\0".encode())
        for a in (s.box_xyxy, s.R, s.t, s.K):
            h.update(np.ascontiguousarray(a, dtype=np.float64).tobytes())
    return h.hexdigest()


def _sources_fingerprint(paths: Sequence[str]) -> str:
    h = hashlib.sha256()
    for p in sorted(paths):
        try:
            st = os.stat(p)
        except FileNotFoundError:
            raise FileNotFoundError(f"{p}: image missing (needed by the crop cache)") from None
        h.update(f"{p}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


@contextlib.contextmanager
def _locked(cache_dir: Path):
    try:
        import fcntl
    except ImportError:  # not POSIX: no cross-process lock
        yield
        return
    with open(cache_dir / _LOCK, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)


# --- worker side -------------------------------------------------------------------------------

_worker_crops = None
_worker_masks = None
_worker_size = 0
_worker_context = 0.0
_worker_filter = "none"


def _init_worker(crops_path: str, size: int, context: float, single_thread: bool = True, masks_path: str = "",
                 crop_filter: str = "none") -> None:
    global _worker_crops, _worker_masks, _worker_size, _worker_context, _worker_filter
    if single_thread:  # worker processes only: never change the caller's OpenCV threading
        cv2.setNumThreads(1)
    _worker_crops = np.load(crops_path, mmap_mode="r+")
    _worker_masks = np.load(masks_path, mmap_mode="r+") if masks_path else None
    _worker_size, _worker_context, _worker_filter = size, context, crop_filter


def read_mask(path: str, image_size) -> np.ndarray:
    """A mask image as stored (``H x W``): BOP ``mask_visib`` 0/255, or a YCB-Video label image of class indices."""
    mask = cv2.imread(path, cv2.IMREAD_UNCHANGED)
    if mask is None:
        raise ValueError(f"{path}: cannot be decoded as an image (needed as a mask by the crop cache)")
    if mask.ndim != 2 or (mask.shape[1], mask.shape[0]) != tuple(image_size):
        raise ValueError(
            f"{path}: a mask must be one channel of {image_size[0]}x{image_size[1]} (its image's size); "
            f"got shape {mask.shape}"
        )
    return mask


def crop_mask(mask: np.ndarray, box_xyxy, size: int, context: float, out=None) -> np.ndarray:
    """Cut a 0/1 mask by the crop rule (bilinear, then threshold at one half); ``S x S`` uint8 0/1."""
    m = preprocess.crop_matrix(box_xyxy, size, context)
    soft = cv2.warpAffine(mask * np.uint8(255), m, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                          borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if out is None:
        out = np.empty((size, size), np.uint8)
    out[...] = soft >= 128
    return out


def _crop_images(tasks) -> int:
    """Decode each image once and write its crops into the shared memmap; returns the crop count."""
    n = 0
    for path, indices, boxes, image_size, masks in tasks:
        image = cv2.imread(path, cv2.IMREAD_COLOR)  # BGR, 3 channels
        if image is None:
            raise ValueError(f"{path}: cannot be decoded as an image (needed by the crop cache)")
        if (image.shape[1], image.shape[0]) != tuple(image_size):
            raise ValueError(
                f"{path}: image is {image.shape[1]}x{image.shape[0]}, but its samples expect "
                f"{image_size[0]}x{image_size[1]} (width x height)"
            )
        decoded = {}  # a YCB-Video label image serves every instance of its frame: decode it once
        for i, box, (mask_path, mask_value) in zip(indices, boxes, masks):
            preprocess.crop_to_square(image, box, _worker_size, _worker_context, out=_worker_crops[i],
                                      crop_filter=_worker_filter)
            if mask_path:
                if mask_path not in decoded:
                    decoded[mask_path] = read_mask(mask_path, image_size)
                raw = decoded[mask_path]
                mask = (raw != 0 if mask_value == 0 else raw == mask_value).astype(np.uint8)
                crop_mask(mask, box, _worker_size, _worker_context, out=_worker_masks[i])
        n += len(indices)
    return n


# --- the cache ---------------------------------------------------------------------------------


class CropCache:
    """Crops of a sample list at the network input size, memory-mapped from disk.

    Build or reuse one with :meth:`build_or_load`; open an existing one without its sources with
    :meth:`open`.

    Attributes:
        crops: ``(N, S, S, 3)`` uint8 read-only memmap, **BGR**, crop ``i`` of ``samples[i]`` by
            :func:`refiner_rt.preprocess.crop_to_square` with this cache's ``size`` and ``context``.
        q_gt: ``(N, 4)`` float64 ground-truth rotations, **wxyz**, ``w >= 0``, object to camera.
        R: ``(N, 3, 3)`` float64 rotations (object to camera); ``t``: ``(N, 3)`` metres.
        K: ``(N, 3, 3)`` float64 intrinsics; ``boxes_xyxy``: ``(N, 4)`` float64 pixels.
        obj_ids, scene_ids, image_paths: ``(N,)`` str arrays; frame_ids: ``(N,)`` int64;
        visib_fract: ``(N,)`` float64, NaN when unknown.
        masks: ``(N, S, S)`` uint8 read-only memmap, 1 on the instance's visible pixels, or None when
            no sample had a mask; has_mask: ``(N,)`` bool (all False without masks).
        size: ``S``; context: the crop rule's context factor; manifest: the build record (dict).
        cache_dir: the folder.

    A ``CropCache`` pickles without its crops (the memmap is reopened on unpickling), so it can be
    handed to DataLoader workers cheaply.
    """

    def __init__(self, cache_dir: str | os.PathLike):
        """Open the cache in ``cache_dir`` as it is (no check against sources; see :meth:`open`)."""
        self.cache_dir = Path(cache_dir)
        manifest_path = self.cache_dir / _MANIFEST
        if not manifest_path.is_file():
            raise FileNotFoundError(f"{manifest_path}: missing; not a (complete) crop cache")
        with open(manifest_path, encoding="utf-8") as f:
            self.manifest = json.load(f)
        if self.manifest.get("format") != CACHE_FORMAT:
            raise ValueError(
                f"{manifest_path}: field 'format' must be {CACHE_FORMAT!r}; got {self.manifest.get('format')!r}"
            )
        self.size = int(self.manifest["size"])
        self.context = float(self.manifest["context"])
        self.crop_filter = str(self.manifest.get("crop_filter", "none"))
        with np.load(self.cache_dir / _INDEX, allow_pickle=False) as index:
            self.q_gt = index["q_gt"]
            self.R = index["R"]
            self.t = index["t"]
            self.K = index["K"]
            self.boxes_xyxy = index["box_xyxy"]
            self.obj_ids = index["obj_id"]
            self.scene_ids = index["scene_id"]
            self.frame_ids = index["frame_id"]
            self.image_paths = index["image_path"]
            self.visib_fract = index["visib_fract"]
            self.has_mask = index["has_mask"] if "has_mask" in index else np.zeros(len(self.q_gt), bool)
        self._open_crops()
        n = int(self.manifest["n"])
        if self.crops.shape != (n, self.size, self.size, 3) or len(self.q_gt) != n:
            raise ValueError(
                f"{self.cache_dir}: inconsistent cache: expected {n} crops of {self.size}x{self.size}x3 and {n} index "
                f"rows; got crops {self.crops.shape}, index {len(self.q_gt)}"
            )

    def _open_crops(self) -> None:
        self.crops = np.load(self.cache_dir / _CROPS, mmap_mode="r")
        masks = self.cache_dir / _MASKS
        self.masks = np.load(masks, mmap_mode="r") if masks.is_file() and self.has_mask.any() else None

    def __len__(self) -> int:
        return len(self.q_gt)

    def __getstate__(self):
        state = self.__dict__.copy()
        del state["crops"], state["masks"]
        return state

    def __setstate__(self, state):
        self.__dict__.update(state)
        self._open_crops()

    def __repr__(self) -> str:
        return f"CropCache({str(self.cache_dir)!r}, n={len(self)}, size={self.size}, context={self.context})"

    def get_batch(self, indices) -> tuple[np.ndarray, np.ndarray]:
        """Copy a batch out of the cache.

        Args:
            indices: ``(B,)`` integer indices.

        Returns:
            ``(crops, q_gt)``: ``(B, S, S, 3)`` uint8 BGR (an in-memory copy) and ``(B, 4)`` float64 wxyz.
        """
        indices = np.asarray(indices, dtype=np.int64)
        return self.crops[indices], self.q_gt[indices]

    @classmethod
    def open(cls, cache_dir: str | os.PathLike) -> "CropCache":
        """Open an existing cache without checking it against samples or source images (e.g. on a
        machine that has the cache but not the dataset)."""
        return cls(cache_dir)

    @classmethod
    def build_or_load(
        cls,
        samples: Sequence[Sample],
        size: int,
        cache_dir: str | os.PathLike,
        *,
        context: float = preprocess.DEFAULT_CONTEXT,
        workers: int | None = 1,
        progress: bool = True,
        crop_filter: str = "none",
    ) -> "CropCache":
        """Return the cache of ``samples`` in ``cache_dir``, building it if it is missing or stale.

        The cache is reused when its manifest matches the sample list (order included), ``size``,
        ``context``, the source images' sizes and mtimes, and the crop rule's code version;
        otherwise it is rebuilt in place (the reason is logged).

        Args:
            samples: the samples, in the order the crops should have.
            size: network input side ``S`` in pixels.
            cache_dir: folder of this cache (created if missing); one folder per (sample list,
                size, context), e.g. ``<data>/.crops/train_base_64``.
            context: crop window side = ``max(w, h) * context`` (the model's ``crop_context``).
            workers: processes that decode and crop (``1``: in this process; ``None``: one per CPU).
                Workers are started with ``spawn`` (safe whatever threads the caller runs), so a
                script that asks for ``workers > 1`` must call this under
                ``if __name__ == "__main__":``; each worker's start-up costs about a second.
            progress: show a tqdm progress bar while building.
            crop_filter: the crop rule's filter (:data:`refiner_rt.preprocess.CROP_FILTERS`; the model's
                ``crop_filter``).

        Returns:
            The opened :class:`CropCache`.

        Raises:
            ValueError: bad arguments, an empty sample list, an image that cannot be decoded or
                whose size differs from its samples' ``image_size``.
            FileNotFoundError: a missing source image.
        """
        samples = list(samples)
        if not samples:
            raise ValueError("samples must not be empty: nothing to cache")
        for s in samples[:1]:
            if not isinstance(s, Sample):
                raise TypeError(f"samples must be models.data.Sample records; got {type(s).__name__}")
        if isinstance(size, bool) or not isinstance(size, (int, np.integer)) or size <= 0:
            raise ValueError(f"size must be a positive integer (crop side in pixels); got {size!r}")
        if not (isinstance(context, (int, float)) and np.isfinite(context) and context > 0):
            raise ValueError(f"context must be a positive number (window side / box side); got {context!r}")
        if crop_filter not in preprocess.CROP_FILTERS:
            raise ValueError(f"crop_filter must be one of {preprocess.CROP_FILTERS}; got {crop_filter!r}")
        if workers is None:
            workers = os.cpu_count() or 1
        if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
            raise ValueError(f"workers must be an integer >= 1 or None; got {workers!r}")
        cache_dir = Path(cache_dir)
        cache_dir.mkdir(parents=True, exist_ok=True)
        expected = cls._expected_manifest(samples, int(size), float(context), crop_filter)
        with _locked(cache_dir):
            reason = cls._stale_reason(cache_dir, expected)
            if reason is None:
                log.info("crop cache %s: up to date (%d crops of %dx%d)", cache_dir, len(samples), size, size)
                return cls(cache_dir)
            log.info("crop cache %s: building (%s)", cache_dir, reason)
            cls._build(samples, int(size), float(context), cache_dir, expected, workers, progress, crop_filter)
            return cls(cache_dir)

    # --- internals ---

    @staticmethod
    def _expected_manifest(samples: list[Sample], size: int, context: float, crop_filter: str = "none") -> dict:
        paths = sorted({s.image_path for s in samples} | {s.mask_path for s in samples if s.mask_path})
        return {
            "format": CACHE_FORMAT,
            "n": len(samples),
            "size": size,
            "context": context,
            "crop_filter": crop_filter,
            "samples_fingerprint": samples_fingerprint(samples),
            "sources_fingerprint": _sources_fingerprint(paths),
            "crop_rule_version": crop_rule_version(),
            "n_images": len(paths),
            "channel_order": "BGR",
            "opencv": cv2.__version__,
        }

    @staticmethod
    def _stale_reason(cache_dir: Path, expected: dict) -> str | None:
        path = cache_dir / _MANIFEST
        if not path.is_file():
            return "no manifest"
        try:
            with open(path, encoding="utf-8") as f:
                found = json.load(f)
        except (OSError, json.JSONDecodeError) as exc:
            return f"unreadable manifest ({exc})"
        changed = [k for k in _KEYS if found.get(k) != expected[k]]
        if changed:
            return "changed: " + ", ".join(changed)
        if not (cache_dir / _CROPS).is_file() or not (cache_dir / _INDEX).is_file():
            return "missing crops or index file"
        return None

    @staticmethod
    def _build(samples, size, context, cache_dir: Path, manifest: dict, workers: int, progress: bool,
               crop_filter: str = "none") -> None:
        from tqdm.auto import tqdm

        start = time.perf_counter()
        (cache_dir / _MANIFEST).unlink(missing_ok=True)  # the cache is invalid until the manifest is back
        n = len(samples)
        tmp_crops = cache_dir / f"crops.tmp-{os.getpid()}.npy"
        np.lib.format.open_memmap(tmp_crops, mode="w+", dtype=np.uint8, shape=(n, size, size, 3)).flush()
        has_mask = np.array([bool(s.mask_path) for s in samples])
        tmp_masks = cache_dir / f"masks.tmp-{os.getpid()}.npy" if has_mask.any() else None
        if tmp_masks is not None:
            np.lib.format.open_memmap(tmp_masks, mode="w+", dtype=np.uint8, shape=(n, size, size)).flush()

        groups: dict[str, list[int]] = {}
        for i, s in enumerate(samples):
            groups.setdefault(s.image_path, []).append(i)
        jobs = [
            (path, idx, [samples[i].box_xyxy for i in idx], samples[idx[0]].image_size,
             [(samples[i].mask_path, samples[i].mask_value) for i in idx])
            for path, idx in groups.items()
        ]
        chunks = [jobs[i : i + _IMAGES_PER_TASK] for i in range(0, len(jobs), _IMAGES_PER_TASK)]
        bar = tqdm(total=n, unit="crop", desc=f"crop cache {cache_dir.name}", disable=not progress, smoothing=0.1)
        try:
            if workers == 1:
                _init_worker(str(tmp_crops), size, context, single_thread=False, masks_path=str(tmp_masks or ""),
                             crop_filter=crop_filter)
                for chunk in chunks:
                    bar.update(_crop_images(chunk))
            else:
                import multiprocessing

                # spawn: a fresh interpreter per worker, safe whatever threads (torch, OpenMP) the parent runs.
                ctx = multiprocessing.get_context("spawn")
                with ctx.Pool(workers, initializer=_init_worker,
                              initargs=(str(tmp_crops), size, context, True, str(tmp_masks or ""),
                                        crop_filter)) as pool:
                    for done in pool.imap_unordered(_crop_images, chunks):
                        bar.update(done)
        except BaseException:
            tmp_crops.unlink(missing_ok=True)
            if tmp_masks is not None:
                tmp_masks.unlink(missing_ok=True)
            raise
        finally:
            bar.close()
            _reset_worker()
        os.replace(tmp_crops, cache_dir / _CROPS)
        if tmp_masks is not None:
            os.replace(tmp_masks, cache_dir / _MASKS)
        else:
            (cache_dir / _MASKS).unlink(missing_ok=True)  # a stale one from an earlier build

        q_gt = rq.from_matrix(np.stack([s.R for s in samples]))
        index = {
            "q_gt": q_gt,
            "R": np.stack([s.R for s in samples]),
            "t": np.stack([s.t for s in samples]),
            "K": np.stack([s.K for s in samples]),
            "box_xyxy": np.stack([s.box_xyxy for s in samples]),
            "obj_id": np.array([s.obj_id for s in samples]),
            "scene_id": np.array([s.scene_id for s in samples]),
            "frame_id": np.array([s.frame_id for s in samples], dtype=np.int64),
            "image_path": np.array([s.image_path for s in samples]),
            "visib_fract": np.array([np.nan if s.visib_fract is None else s.visib_fract for s in samples]),
            "has_mask": has_mask,
        }
        tmp_index = cache_dir / f"index.tmp-{os.getpid()}.npz"
        with open(tmp_index, "wb") as f:
            np.savez(f, **index)
        os.replace(tmp_index, cache_dir / _INDEX)

        seconds = time.perf_counter() - start
        record = dict(manifest, build_seconds=round(seconds, 3), workers=workers, created=time.strftime("%Y-%m-%dT%H:%M:%S"))
        tmp_manifest = cache_dir / f"manifest.tmp-{os.getpid()}.json"
        with open(tmp_manifest, "w", encoding="utf-8") as f:
            json.dump(record, f, indent=1, sort_keys=True)
        os.replace(tmp_manifest, cache_dir / _MANIFEST)
        log.info(
            "crop cache %s: %d crops from %d images in %.1f s (%.0f crops/s, %d worker(s))",
            cache_dir, n, len(jobs), seconds, n / max(seconds, 1e-9), workers,
        )


def _reset_worker() -> None:
    global _worker_crops, _worker_masks
    for memmap in (_worker_crops, _worker_masks):
        if memmap is not None:
            memmap.flush()
    _worker_crops = _worker_masks = None
