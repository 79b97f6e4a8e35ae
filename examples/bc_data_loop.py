"""Behaviour cloning's data loop over AGOS-Dataset (docs/DATASET.md, "On disk"; docs/LIBRARY.md): read
the expert's decisions of a few episodes from the dataset's own files, turn each into (camera image,
legal actions) -> the expert's action, and fit a softmax regression in numpy. No training framework:
the point is the loop; put your model where :func:`fit` updates ``weights``.

    python -m examples.bc_data_loop data/sample --role uav --episodes 4
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import get_args

import cv2
import numpy as np

from agos.runtime.schemas import Role, UavActionName, UgvActionName

ACTIONS: dict[Role, list[str]] = {"uav": list(get_args(UavActionName)), "ugv": list(get_args(UgvActionName))}
"""The classes: each role's action names (the label is the expert's action's index here)."""
CAMERA = {"uav": ("nadir",), "ugv": ("forward", "front")}
"""The view a decision is learnt from: the UAV's nadir image; the UGV's forward one (the front of its six)."""


@dataclass(frozen=True)
class Example:
    image: np.ndarray
    """The camera's RGB image, ``size x size x 3`` float32 in [0, 1]."""
    legal: np.ndarray
    """1 for each of the role's actions legal at the decision (``ACTIONS[role]`` order)."""
    label: int
    """The expert's action, its index in ``ACTIONS[role]``."""
    decision: dict
    """The decision's line of ``decisions.jsonl`` (time, pose, the expert's whole reply ...)."""


def decisions(dataset: Path, role: Role, episodes: int | None = None) -> Iterator[dict]:
    """The role's decisions, episode by episode (sorted by id), as ``decisions.jsonl`` holds them."""
    folders = sorted(p for p in (dataset / "episodes").iterdir() if p.is_dir())
    for folder in folders[:episodes]:
        with (folder / role / "decisions.jsonl").open() as lines:
            yield from (json.loads(line) for line in lines if line.strip())


def examples(dataset: Path, role: Role, *, episodes: int | None = None, size_px: int = 32) -> Iterator[Example]:
    """Each decision as an :class:`Example`, its image read from the file the decision names."""
    for line in decisions(dataset, role, episodes):
        view = next(i for name in CAMERA[role] for i in line["images"] if i["name"] == name and i["kind"] == "rgb")
        bgr = cv2.imread(str(dataset / view["path"]), cv2.IMREAD_COLOR)
        if bgr is None:
            raise FileNotFoundError(f"{dataset / view['path']}: the image decision {line['decision_index']} names")
        image = cv2.resize(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB), (size_px, size_px), interpolation=cv2.INTER_AREA)
        legal = np.array([name in line["legal_actions"] for name in ACTIONS[role]], np.float32)
        yield Example(image.astype(np.float32) / 255.0, legal, ACTIONS[role].index(line["action"]["action"]), line)


def batches(items: list[Example], batch_size: int, rng: np.random.Generator) -> Iterator[tuple[np.ndarray, np.ndarray,
                                                                                              np.ndarray]]:
    """Shuffled batches of (features, legal masks, labels): features are the flattened image and the mask."""
    order = rng.permutation(len(items))
    for start in range(0, len(items), batch_size):
        chosen = [items[k] for k in order[start:start + batch_size]]
        legal = np.stack([e.legal for e in chosen])
        features = np.concatenate([np.stack([e.image.ravel() for e in chosen]), legal], axis=1)
        yield features, legal, np.array([e.label for e in chosen])


def fit(dataset: Path, role: Role, *, episodes: int | None = None, epochs: int = 20, batch_size: int = 16,
        learning_rate: float = 0.5, seed: int = 0) -> tuple[float, int]:
    """Softmax regression on the role's decisions, illegal actions masked out; (training accuracy,
    number of decisions)."""
    items = list(examples(dataset, role, episodes=episodes))
    rng = np.random.default_rng(seed)
    n_features = items[0].image.size + len(ACTIONS[role])
    weights = np.zeros((n_features, len(ACTIONS[role])), np.float32)
    for _ in range(epochs):
        for features, legal, labels in batches(items, batch_size, rng):
            probs = _softmax(features @ weights, legal)
            probs[np.arange(len(labels)), labels] -= 1.0  # the gradient of the cross-entropy
            weights -= learning_rate * features.T @ probs / len(labels)
    features, legal, labels = next(batches(items, len(items), rng))
    return float((_softmax(features @ weights, legal).argmax(axis=1) == labels).mean()), len(items)


def _softmax(logits: np.ndarray, legal: np.ndarray) -> np.ndarray:
    logits = np.where(legal > 0, logits, -np.inf)
    exp = np.exp(logits - logits.max(axis=1, keepdims=True))
    return exp / exp.sum(axis=1, keepdims=True)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path, help="a dataset folder (agos dataset build --out DIR)")
    parser.add_argument("--role", choices=["uav", "ugv"], default="uav")
    parser.add_argument("--episodes", type=int, help="the first N episodes (default all)")
    args = parser.parse_args()
    accuracy, n = fit(args.dataset, args.role, episodes=args.episodes)
    print(f"{args.role}: {n} decisions, training accuracy {accuracy:.2f}")
