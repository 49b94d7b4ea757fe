"""Training input pipeline, host side: decode photos and cut random crops (paper section 5).

The paper trains on 240x320 colour crops of the 118,287 MS COCO train2017 images. The host only
decodes and crops; homographies, warps and photometric augmentation happen on the device inside
the jitted step. Sources, chosen by ``DataConfig.source``:

* ``sample``: the real photos shipped inside installed packages (scikit-image, matplotlib and,
  when installed, scikit-learn); works offline on a fresh install.
* a folder, searched recursively for .jpg .jpeg .png .ppm .pgm .bmp .tif .tiff .webp (any case),
  e.g. the corpus that ``experiments/build_corpus.py`` assembles.
* ``tfds:NAME[:SPLIT]`` (split defaults to ``train``), a TFDS dataset prepared in the
  ``array_record`` format, read without TensorFlow. Preparing COCO needs TensorFlow and internet
  once, on any machine::

      pip install tensorflow tensorflow-datasets
      tfds build coco/2017 --file_format=array_record --data_dir=DIR

  then copy ``DIR`` to the training machine and use ``source="tfds:coco/2017"`` with
  ``tfds_data_dir=DIR`` (or set ``TFDS_DATA_DIR``). Any dataset with an ``image`` feature works.
* ``pairs:FOLDER``: two views of a 3-D scene per example, with depth and relative pose
  (``training.pairs``); a batch is then a dict of both images and their point maps, and the
  step trains on the scene's own geometry instead of a random homography.

``make_dataset`` returns a grain ``MapDataset`` of batches: batch ``step`` is a pure function of
(seed, step), so a run resumed at step s sees exactly the batches an uninterrupted run would.
"""

from __future__ import annotations

import abc
import dataclasses
import logging
import pathlib
import threading
import time
from collections.abc import Iterator, Sequence

import grain
import numpy as np

from usp_jax.inference.images import IMAGE_SUFFIXES, decode_image, sample_photos
from usp_jax.training import pairs
from usp_jax.training.crops import context_side, random_context_crop, random_crop

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Where training photos come from and how crops are cut from them.

    Crop geometry (see ``random_crop``): the crop window has the output's aspect ratio and a side
    that is a fraction f ~ U(scale_range) of the largest such window that fits in the photo, and
    is resized to ``height`` x ``width``. f = 1 is the whole photo (a 480x640 COCO image halved,
    as in the paper); f = 0.5 a native-resolution 240x320 patch of it. f is raised where needed
    so that a window is never smaller than the output: photos are only ever upsampled when they
    are smaller than the crop, and then only as ``small_images`` allows.

    ``small_images``: "upscale" (default) enlarges a photo smaller than the crop to cover it;
    "skip" replaces it by the next usable photo. Upscaling is the default because skipping
    changes which photos are trained on without the user asking: the ``sample`` source has two
    scans 172 and 191 px tall, and COCO a few hundred images under 240 px.

    ``context_window``: deliver, per example, a square context window around the crop instead of
    the crop (``random_context_crop``): side ``context_side(height, width)``, the crop's diagonal,
    at the crop's pixel scale, with the crop at its centre and a fourth, validity channel. Training
    then renders branch B from the whole window (``train.make_window_branches``), so the random
    homography may rotate by any angle (``HomographyConfig.rotation_range``) and B still shows real
    photo content. Off (the default), batches are the crops themselves, exactly as before.
    """

    source: str = "sample"
    height: int = 240
    width: int = 320
    scale_range: tuple[float, float] = (0.5, 1.0)
    small_images: str = "upscale"
    # Decode threads: OpenCV releases the GIL while decoding and resizing, so threads scale and
    # the count of skipped images stays in one process.
    num_workers: int = 4
    # Batches decoded ahead of the training step; at least num_workers keeps every thread busy.
    prefetch: int = 8
    # Seeds the image order alone; None derives it from the run seed. Fixing it lets runs with
    # different seeds see the same photos in the same order (crops still follow the run seed).
    shuffle_seed: int | None = None
    # Where tfds: sources are prepared; "" means TFDS's default ($TFDS_DATA_DIR or
    # ~/tensorflow_datasets).
    tfds_data_dir: str = ""
    context_window: bool = False

    def __post_init__(self):
        low, high = self.scale_range
        if not 0 < low <= high <= 1:
            raise ValueError(f"scale_range {self.scale_range} must satisfy 0 < low <= high <= 1")
        if self.small_images not in ("upscale", "skip"):
            raise ValueError(f"small_images {self.small_images!r} must be 'upscale' or 'skip'")
        if self.height < 1 or self.width < 1:
            raise ValueError(f"crop size {self.height}x{self.width} must be positive")
        if self.context_window and self.source.startswith(pairs.PREFIX):
            raise ValueError(
                "context_window=True draws homographies of a photo; a pairs: source brings "
                "its own geometry"
            )

    @property
    def example_shape(self) -> tuple[int, int, int]:
        """Shape of one example of a batch: [height, width, 3], or [S, S, 4] with a context window."""
        if self.context_window:
            side = context_side(self.height, self.width)
            return side, side, 4
        return self.height, self.width, 3


# ----------------------------------------------------------------------------------------------
# Sources


class Source(abc.ABC):
    """Random access to photos: ``len(source)``, ``source[i]`` -> uint8 [H, W, 3] RGB."""

    @abc.abstractmethod
    def __len__(self) -> int: ...

    @abc.abstractmethod
    def name(self, index: int) -> str:
        """What to call photo ``index`` in messages (a file path, or dataset[split][index])."""

    @abc.abstractmethod
    def read(self, index: int) -> bytes:
        """The encoded bytes of photo ``index``."""

    def __getitem__(self, index: int) -> np.ndarray:
        """Photo ``index`` as uint8 [H, W, 3] RGB; ValueError/OSError if it is unreadable."""
        return decode_image(self.read(index), self.name(index))


class FileSource(Source):
    """Image files, in the order given."""

    def __init__(self, paths: Sequence[pathlib.Path]):
        self.paths = tuple(paths)

    def __len__(self) -> int:
        return len(self.paths)

    def name(self, index: int) -> str:
        return str(self.paths[index])

    def read(self, index: int) -> bytes:
        return self.paths[index].read_bytes()


class TfdsSource(Source):
    """The ``image`` feature of a prepared TFDS split, left encoded so that OpenCV decodes it."""

    def __init__(self, data_source, label: str):
        self.data_source = data_source
        self.label = label

    def __len__(self) -> int:
        return len(self.data_source)

    def name(self, index: int) -> str:
        return f"{self.label}[{index}]"

    def read(self, index: int) -> bytes:
        return self.data_source[index]["image"]


class PairSource:
    """Two-view pairs with depth and pose (``training.pairs``), one folder each."""

    def __init__(self, spec: str):
        self.folders = pairs.pair_folders(spec)

    def __len__(self) -> int:
        return len(self.folders)

    def name(self, index: int) -> str:
        return str(self.folders[index])

    def __getitem__(self, index: int) -> pairs.ViewPair:
        """Pair ``index``; ValueError/OSError if a file of it is missing or unreadable."""
        return pairs.read_pair(self.folders[index])


def _folder_source(spec: str) -> FileSource:
    root = pathlib.Path(spec).expanduser()
    if not root.exists():
        raise FileNotFoundError(f"image folder {spec} does not exist")
    if not root.is_dir():
        raise ValueError(f"image source {spec} is not a folder (nor 'sample' or 'tfds:NAME')")
    # Sorted so that every host and every run index the same photo by the same number.
    paths = sorted(p for p in root.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES and p.is_file())
    if not paths:
        raise ValueError(f"image folder {spec} holds no {'/'.join(IMAGE_SUFFIXES)} files")
    return FileSource(paths)


def _tfds_source(spec: str, data_dir: str) -> TfdsSource:
    # Imported here: tensorflow_datasets takes a second to import and only this source needs it.
    import tensorflow_datasets as tfds
    from tensorflow_datasets.core import read_only_builder

    name, _, split = spec.removeprefix("tfds:").partition(":")
    split = split or "train"
    where = data_dir or "the default TFDS data dir"
    # Prepared files, not the registered builder code: tfds.data_source(name) constructs the
    # builder class first, and some (coco) touch TensorFlow there even when the array_record
    # files are on disk. This is the read-only path tfds.data_source takes for versioned names.
    try:
        builder = read_only_builder.builder_from_files(name, data_dir=data_dir or None)
    except tfds.core.DatasetNotFoundError:
        raise ValueError(
            f"TFDS dataset {name!r} ({spec}) is not prepared in {where}; prepare it with "
            f"`tfds build {name} --file_format=array_record`"
        ) from None
    if "image" not in builder.info.features:
        raise ValueError(f"TFDS dataset {name!r} ({spec}) has no 'image' feature")
    try:
        data_source = builder.as_data_source(
            split=split, decoders={"image": tfds.decode.SkipDecoding()}
        )
    except (ValueError, NotImplementedError) as error:  # Unknown split, non-random-access format.
        message = str(error).splitlines()[0]
        raise ValueError(f"TFDS source {spec} in {where}: {message}") from None
    return TfdsSource(data_source, f"{name}[{split}]")


def open_source(spec: str, *, tfds_data_dir: str = "") -> Source | PairSource:
    """Opens ``sample``, ``tfds:NAME[:SPLIT]``, ``pairs:FOLDER`` or a folder path (see the module
    docstring).

    Raises FileNotFoundError for a missing folder, ValueError for an empty one or an unknown or
    unprepared TFDS dataset, each naming it. (A folder named ``sample`` is ``./sample``.)
    """
    if spec == "sample":
        photos = sample_photos()
        if not photos:
            raise ValueError("source 'sample': no photo found in the installed scikit-image")
        return FileSource([path for _, path in photos])
    if spec.startswith("tfds:"):
        return _tfds_source(spec, tfds_data_dir)
    if spec.startswith(pairs.PREFIX):
        return PairSource(spec)
    return _folder_source(spec)


# ----------------------------------------------------------------------------------------------
# Pipeline


class SkipLog:
    """Thread-safe record of the source photos the pipeline could not use, each logged once."""

    def __init__(self):
        self._reasons: dict[int, str] = {}
        self._lock = threading.Lock()

    def add(self, index: int, reason: str) -> None:
        with self._lock:
            if index in self._reasons:
                return
            self._reasons[index] = reason
        log.warning("skipping %s", reason)

    def __contains__(self, index: int) -> bool:
        return index in self._reasons

    def __len__(self) -> int:
        return len(self._reasons)

    def reasons(self) -> list[str]:
        """One line per skipped photo, naming it and why."""
        with self._lock:
            return list(self._reasons.values())


@dataclasses.dataclass(frozen=True)
class Pipeline:
    """What ``make_dataset`` returns: the batches and the record of skipped photos.

    ``pipeline[step]`` (or ``pipeline.batches[step]``) is this process's uint8
    [batch_size, height, width, 3] share of global batch ``step`` ([batch_size, S, S, 4] context
    windows with ``DataConfig.context_window``; see ``DataConfig.example_shape``).
    """

    batches: grain.MapDataset
    source: Source | PairSource
    skipped: SkipLog
    read_options: grain.ReadOptions

    def __getitem__(self, step: int) -> np.ndarray | dict[str, np.ndarray]:
        return self.batches[step]


def _usable_crop(
    index: int,
    rng: np.random.Generator,
    *,
    source: Source | PairSource,
    config: DataConfig,
    skipped: SkipLog,
) -> np.ndarray | dict[str, np.ndarray]:
    """A crop of photo ``index``, or of the next usable one after it (wrapping around); from a
    ``PairSource``, the example of pair ``index`` (``pairs.example``) or of the next usable one.

    Substituting the next usable photo keeps batch shapes fixed and depends only on the files, so
    it is as deterministic as the rest of the pipeline. ``rng`` is drawn from only by the crop.
    """
    for offset in range(len(source)):
        i = (index + offset) % len(source)
        if i in skipped:
            continue
        try:
            image = source[i]
        except (OSError, ValueError) as error:
            skipped.add(
                i, f"unreadable {'pair' if isinstance(source, PairSource) else 'image'} {error}"
            )
            continue
        if isinstance(source, PairSource):
            return pairs.example(image, config.height, config.width, rng)
        if config.small_images == "skip" and (
            image.shape[0] < config.height or image.shape[1] < config.width
        ):
            skipped.add(
                i,
                f"{source.name(i)}: {image.shape[0]}x{image.shape[1]} is smaller than the "
                f"{config.height}x{config.width} crop (small_images='skip')",
            )
            continue
        if config.context_window:
            return random_context_crop(rng, image, config.height, config.width, config.scale_range)
        return random_crop(rng, image, config.height, config.width, config.scale_range)
    raise ValueError(
        f"source {config.source!r}: none of its {len(source)} images is usable "
        "(all unreadable or, with small_images='skip', smaller than the crop)"
    )


_EPOCHS_LIMIT = 2**53  # crops per pipeline before it ends: ~10^8 years of training at 10^3/s


def make_dataset(
    config: DataConfig,
    batch_size: int,
    *,
    seed: int,
    process_index: int = 0,
    process_count: int = 1,
) -> Pipeline:
    """Endless shuffled batches of random crops: ``make_dataset(...)[step]`` is uint8
    [batch_size, config.height, config.width, 3] (with ``config.context_window``, the crops'
    context windows, [batch_size, S, S, 4], see ``random_context_crop``), a pure function of
    (seed, step).

    ``batch_size`` is per process. Global batch ``step`` is the concatenation over processes of
    their batches, process p holding rows [p * batch_size, (p + 1) * batch_size); each process
    decodes only its own rows. Epochs are reshuffled; a photo that cannot be used is replaced by
    the next usable one and counted (``stats``). Raises at once if the source cannot be opened
    or holds no usable photo.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size {batch_size} must be positive")
    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index {process_index} is not in [0, {process_count})")
    source = open_source(config.source, tfds_data_dir=config.tfds_data_dir)
    skipped = SkipLog()

    def crop(index: int, rng: np.random.Generator) -> np.ndarray:
        return _usable_crop(index, rng, source=source, config=config, skipped=skipped)

    # Fails here, not in a worker thread, when no photo is usable.
    crop(0, np.random.default_rng(0))
    crops = (
        grain.MapDataset.range(len(source))
        .seed(seed)
        .shuffle(seed=config.shuffle_seed)
        # Endless in practice; grain's infinite repeat has length sys.maxsize, which a batch of 1
        # keeps and Python's len() then cannot return.
        .repeat(_EPOCHS_LIMIT // len(source))
        .random_map(crop)
    )
    # Global batch s holds crops [s * B, (s + 1) * B), B = batch_size * process_count: runs of
    # batch_size crops, of which process p takes run s * process_count + p.
    batches = crops.batch(batch_size)[process_index::process_count]
    read_options = grain.ReadOptions(
        num_threads=config.num_workers, prefetch_buffer_size=config.prefetch
    )
    return Pipeline(batches, source, skipped, read_options)


def iterate(dataset: Pipeline, start_step: int = 0) -> Iterator[np.ndarray]:
    """Batches ``start_step``, ``start_step + 1``, ..., decoded ahead by background threads."""
    return iter(dataset.batches[start_step:].to_iter_dataset(dataset.read_options))


def stats(dataset: Pipeline) -> dict[str, int]:
    """Counters for the training log: photos skipped so far (warnings name each one)."""
    return {"skipped_images": len(dataset.skipped)}


def measure_throughput(config: DataConfig, batch_size: int, steps: int) -> float:
    """Decoded and cropped images per second over ``steps`` batches after a first warm-up one."""
    batches = iterate(make_dataset(config, batch_size, seed=0))
    next(batches)
    start = time.perf_counter()
    for _ in range(steps):
        next(batches)
    return steps * batch_size / (time.perf_counter() - start)
