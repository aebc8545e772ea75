"""nuScenes' 13 JSON tables, loaded and indexed without the devkit.

A nuScenes version (``v1.0-mini``, ``v1.0-trainval``) is a folder ``<dataroot>/<version>/`` holding
one JSON list per table; every record has a ``token`` (its primary key) and refers to others by
``*_token`` fields (``""`` = no link). :class:`NuScenesTables` loads them all, indexes them by
token, and resolves links with :meth:`NuScenesTables.get`, which names the table, the record and
the field of a link that leads nowhere (:class:`NuScenesError`).

Reverse indexes (what the devkit adds on load): sample_data and sample_annotation by sample
token, and each calibrated sensor's channel and modality.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import Any

from phigenesis.errors import SourceError

#: The tables of a nuScenes version, all required.
TABLE_NAMES: tuple[str, ...] = (
    "attribute",
    "calibrated_sensor",
    "category",
    "ego_pose",
    "instance",
    "log",
    "map",
    "sample",
    "sample_annotation",
    "sample_data",
    "scene",
    "sensor",
    "visibility",
)

Record = dict[str, Any]


class NuScenesError(SourceError):
    """A nuScenes dataset is incomplete or inconsistent; the message names the table, the token
    or the file."""


class NuScenesTables:
    """All tables of one version, indexed by token.

    Attributes:
        root: the version folder (``<dataroot>/<version>``).
        tables: table name -> {token: record}.
    """

    def __init__(self, dataroot: str | Path, version: str):
        self.dataroot = Path(dataroot).expanduser()
        self.version = version
        self.root = self.dataroot / version
        if not self.root.is_dir():
            raise NuScenesError(f"{self.root}: no such nuScenes version folder")
        self.tables: dict[str, dict[str, Record]] = {name: self._load(name) for name in TABLE_NAMES}
        self.sample_data_by_sample: dict[str, list[Record]] = defaultdict(list)
        for sd in self.tables["sample_data"].values():
            self.sample_data_by_sample[sd.get("sample_token", "")].append(sd)
        self.annotations_by_sample: dict[str, list[Record]] = defaultdict(list)
        for ann in self.tables["sample_annotation"].values():
            self.annotations_by_sample[ann.get("sample_token", "")].append(ann)

    def _load(self, name: str) -> dict[str, Record]:
        path = self.root / f"{name}.json"
        if not path.is_file():
            raise NuScenesError(f"{path}: table {name!r} is missing (a nuScenes version needs all 13 tables)")
        try:
            rows = json.loads(path.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as e:
            raise NuScenesError(f"{path}: table {name!r} is not valid JSON ({e})") from None
        if not isinstance(rows, list):
            raise NuScenesError(f"{path}: table {name!r} must be a JSON list of records")
        out: dict[str, Record] = {}
        for i, row in enumerate(rows):
            if not isinstance(row, dict) or not isinstance(row.get("token"), str):
                raise NuScenesError(f"{path}: record {i} of table {name!r} has no token")
            out[row["token"]] = row
        return out

    def __getitem__(self, table: str) -> dict[str, Record]:
        return self.tables[table]

    def get(self, table: str, token: str, referrer: str = "") -> Record:
        """The record ``token`` of ``table``; ``referrer`` (e.g. ``"sample_data abc.ego_pose_token"``)
        says where the link came from, for the error."""
        rec = self.tables[table].get(token)
        if rec is None:
            via = f" (referenced by {referrer})" if referrer else ""
            raise NuScenesError(f"table {table!r} has no record with token {token!r}{via}")
        return rec

    def follow(self, table_of_record: str, record: Record, field: str, target: str) -> Record:
        """The record of ``target`` that ``record[field]`` points to."""
        token = record.get(field)
        if not isinstance(token, str):
            raise NuScenesError(f"{table_of_record} {record['token']!r} has no field {field!r}")
        return self.get(target, token, f"{table_of_record} {record['token']!r}.{field}")

    def channel(self, sample_data: Record) -> tuple[str, str]:
        """(channel, modality) of a sample_data record, through its calibrated sensor."""
        cs = self.follow("sample_data", sample_data, "calibrated_sensor_token", "calibrated_sensor")
        sensor = self.follow("calibrated_sensor", cs, "sensor_token", "sensor")
        return str(sensor["channel"]), str(sensor["modality"])

    def scene_samples(self, scene: Record) -> list[Record]:
        """The samples of ``scene`` in time order, by its ``first_sample_token`` and ``next`` links."""
        out: list[Record] = []
        seen: set[str] = set()
        sample = self.follow("scene", scene, "first_sample_token", "sample")
        while True:
            if sample["token"] in seen:
                raise NuScenesError(
                    f"sample {sample['token']!r}: the next links of scene {scene['name']} loop"
                )
            seen.add(sample["token"])
            if sample.get("scene_token") != scene["token"]:
                raise NuScenesError(
                    f"sample {sample['token']!r} is linked from scene {scene['name']!r} "
                    f"but its scene_token is {sample.get('scene_token')!r}"
                )
            out.append(sample)
            if not sample.get("next"):
                return out
            sample = self.follow("sample", sample, "next", "sample")
