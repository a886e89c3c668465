"""Train the ``floornet`` floor network on every labelled shared image and export the
ONNX file the daemon ships (app/perception/models/floor_net.onnx).

    .venv/bin/pip install -e '.[train]'
    .venv/bin/python scripts/train_floor_net.py [--datasets DIR] [--out PATH] [--seed N]

Its out-of-scene accuracy is measured by ``floornav eval --cv --method floornet``, which
trains the same network once per fold without the held-out scenes. Every training
constant lives in `app.training.floor_net` and was fixed before any held-out score.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from app.config import PerceptionConfig  # noqa: E402
from app.evaluation import list_labelled_images  # noqa: E402
from app.imageio import read_bgr, read_mask  # noqa: E402
from app.perception.floor_net import DEFAULT_MODEL_PATH  # noqa: E402
from app.perception.pipeline import trapezoid_from_config  # noqa: E402
from app.training.floor_net import export_onnx, prepare, train  # noqa: E402

DATASETS = ("robot-hand-floor", "hospital-ground", "umd-drivable-toy")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--datasets", type=Path, default=ROOT.parent / "shared" / "datasets")
    parser.add_argument("--out", type=Path, default=DEFAULT_MODEL_PATH)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    images = []
    for dataset in DATASETS:
        listing = list_labelled_images(args.datasets / dataset)
        for item in listing.items:
            frame = read_bgr(item.image_path)
            images.append(prepare(frame, read_mask(item.mask_path, frame.shape[:2])))
        print(f"{dataset}: {len(listing.items)} images", file=sys.stderr)
    if not images:
        print(f"no labelled images under {args.datasets}", file=sys.stderr)
        return 1
    zone = trapezoid_from_config(PerceptionConfig().safe_zone)
    started = time.perf_counter()

    def report(epoch: int, loss: float) -> None:
        if epoch % 10 == 0:
            elapsed = time.perf_counter() - started
            print(f"epoch {epoch}: loss {loss:.4f} ({elapsed:.0f} s)", file=sys.stderr)

    model = train(images, zone, seed=args.seed, progress=report)
    export_onnx(model, args.out)
    size_kb = args.out.stat().st_size / 1024
    print(f"wrote {args.out} ({size_kb:.0f} KB) from {len(images)} images")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
