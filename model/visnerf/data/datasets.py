"""One reader for every dataset and every command: training, evaluation, the hold-out and calibration.

A dataset is a folder with ``transforms_<split>.json`` files (NeRF-Blender, D-NeRF, nerfstudio
keys) or a Cinema database (a folder with ``data.csv``; every row is a frame, and the database is
its one split). Both give a ``ParsedSplit``: the frames, their cameras and the full parameter
table, so that no command reads parameters by rules of its own.
"""

from pathlib import Path

from visnerf.data.errors import DatasetError
from visnerf.data.parsers.blender import ParsedSplit, read_transforms
from visnerf.data.parsers.cinema import is_cinema_database, read_cinema
from visnerf.data.parsers.cinema_cameras import CinemaCamera
from visnerf.data.scene import SceneData

SPLITS = ("train", "val", "test")

__all__ = ["SPLITS", "DatasetError", "ParsedSplit", "has_split", "is_cinema_database", "load_dataset", "read_split"]


def has_split(folder: str | Path, split: str) -> bool:
    """Whether the dataset has ``split``: a Cinema database has one, read as ``train``."""
    folder = Path(folder)
    if is_cinema_database(folder):
        return split == "train"
    return (folder / f"transforms_{split}.json").is_file()


def read_split(folder: str | Path, split: str = "train", cinema: CinemaCamera | None = None) -> ParsedSplit:
    """One split of the dataset at ``folder`` (a Cinema database: all its rows, under any split name
    the caller asks for, since it has only one)."""
    folder = Path(folder)
    if is_cinema_database(folder):
        return read_cinema(folder, cinema)
    if not folder.is_dir():
        raise DatasetError(f"dataset folder {folder} does not exist")
    if cinema is not None and cinema != CinemaCamera():
        raise DatasetError(f"{folder} is not a Cinema database: the Cinema camera options do not apply to it")
    path = folder / f"transforms_{split}.json"
    if not path.is_file():
        present = sorted(p.name for p in folder.glob("transforms_*.json"))
        raise DatasetError(f"transforms file {path} does not exist (present: "
                           f"{', '.join(present) if present else 'none; nor is there a Cinema data.csv'})")
    return read_transforms(path)


def load_dataset(folder: str | Path, split: str = "train", cinema: CinemaCamera | None = None) -> SceneData:
    """The frames of one split (``read_split``)."""
    return read_split(folder, split, cinema).scene
