"""Which labelled images come from the same place: the unit of honest cross-validation.

Frames of one video, or photos of one place, share floor, light and furniture; a model
tested on a frame whose neighbours it was fitted on scores what it memorised. So every
accuracy figure holds whole scenes out (``floornav eval --cv``).

Scenes, from each dataset's ``SOURCE.md`` and file names:

- ``robot-hand-floor``: ``robot_hand_<SEQUENCE>_f<FRAME>.jpg``, one scene per video
  sequence (e.g. ``Library_01``).
- ``hospital-ground``: ``floor<N>.jpg``, unrelated stock photos of different hospitals
  and rooms, one scene each.
- ``umd-drivable-toy``: consecutive frames of one robot run, one scene.
- Any other folder: one scene per file name with a trailing frame number removed
  (``name_f000123``, ``name-0042``, ``name0042``), so numbered frames stay together.
"""

from __future__ import annotations

import re

_ROBOT_HAND = re.compile(r"^robot_hand_(?P<sequence>.+)_f\d+$")
_TRAILING_FRAME = re.compile(r"^(?P<stem>.*?)[_-]?f?\d+$")


def scene_of(dataset: str, stem: str) -> str:
    """The scene id of image ``stem`` (file name without extension) in ``dataset``.

    Examples
    --------
    >>> scene_of("robot-hand-floor", "robot_hand_Library_01_f000042")
    'robot-hand-floor/Library_01'
    >>> scene_of("hospital-ground", "floor17")
    'hospital-ground/floor17'
    >>> scene_of("umd-drivable-toy", "A00002")
    'umd-drivable-toy'
    >>> scene_of("my-flat", "kitchen_f000120")
    'my-flat/kitchen'
    """
    if dataset == "robot-hand-floor":
        match = _ROBOT_HAND.match(stem)
        if match:
            return f"{dataset}/{match['sequence']}"
    if dataset == "hospital-ground":
        return f"{dataset}/{stem}"
    if dataset == "umd-drivable-toy":
        return dataset
    match = _TRAILING_FRAME.match(stem)
    base = match["stem"] if match and match["stem"] else stem
    return f"{dataset}/{base}"


def scene_folds(scenes: list[str], n_folds: int | None) -> list[list[str]]:
    """Split distinct scenes into folds of whole scenes.

    ``n_folds=None`` (or >= the number of scenes) gives leave-one-scene-out. Otherwise
    scenes are dealt round-robin in sorted order, which is deterministic and keeps a
    dataset's scenes spread over the folds.
    """
    distinct = sorted(set(scenes))
    if n_folds is None or n_folds >= len(distinct):
        return [[scene] for scene in distinct]
    if n_folds < 2:
        raise ValueError(f"cross-validation needs at least 2 folds, got {n_folds}")
    folds: list[list[str]] = [[] for _ in range(n_folds)]
    for index, scene in enumerate(distinct):
        folds[index % n_folds].append(scene)
    return folds
