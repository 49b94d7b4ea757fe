"""OpenCV's graf1 -> graf3 sample pair (from the opencv-doc package, see build_corpus.py) as an
Oxford-layout scene, so ``usp-jax evaluate`` reads it like any other::

    python3 experiments/graf_pair.py --graf data/corpus/graf --out data/graf
    usp-jax evaluate --hpatches data/graf --res 480x640 --top 1000

``H1to3p.xml`` holds the homography (node ``H13``, graf1 -> graf3); it is written as the plain
text ``H1to2p`` of a two-image scene ``img1.png`` (graf1), ``img2.png`` (graf3).
"""

import argparse
import pathlib
import shutil

import cv2
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--graf", type=pathlib.Path, required=True, help="folder with graf1/3")
    parser.add_argument("--out", type=pathlib.Path, required=True)
    args = parser.parse_args()
    storage = cv2.FileStorage(str(args.graf / "H1to3p.xml"), cv2.FILE_STORAGE_READ)
    homography = storage.getNode("H13").mat()
    if homography is None or homography.shape != (3, 3):
        raise SystemExit(f"{args.graf / 'H1to3p.xml'} holds no 3x3 node H13")
    scene = args.out / "graf"
    scene.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(args.graf / "graf1.png", scene / "img1.png")
    shutil.copyfile(args.graf / "graf3.png", scene / "img2.png")
    np.savetxt(scene / "H1to2p", homography)
    print(f"wrote {scene}")


if __name__ == "__main__":
    main()
