"""A parameter set the worker marked unfit (validates worse than CAD, physically impossible) is
kept in the store but never uploaded unless the operator forces it (issue 21, case 5)."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest

from robid_link.config import load_daemon_config
from robid_link.exceptions import ApprovalError
from robid_link.jobs import PARAMETER_SET_FORMAT, set_sha256
from robid_link.link.campaign import upload_set
from robid_link.link.driver import parameter_bytes
from robid_link.link.store import SqliteStore

from .conftest import QUICK, write_config


class _Recorder:
    """A driver's upload side: remembers what it was asked to load."""

    def __init__(self) -> None:
        self.loaded: list[dict[str, Any]] = []

    async def upload_parameters(self, doc: dict[str, Any], *, timeout_s: float) -> None:
        self.loaded.append(doc)


def _set(uploadable: bool) -> dict[str, Any]:
    doc: dict[str, Any] = {"format": PARAMETER_SET_FORMAT, "robot": "arm3", "run_id": "r1",
                           "base_parameters": [], "uploadable": uploadable,
                           "unfit": [] if uploadable else [
                               "physically impossible: zz_1 = -63.3 ± 27; refit with "
                               "--method consistent"]}
    doc["sha256"] = set_sha256(doc)
    return doc


def test_an_unfit_set_is_refused_unless_forced(tmp_path: Path) -> None:
    async def go() -> tuple[list[str], int]:
        drv = _Recorder()
        async with SqliteStore(tmp_path / "state") as store:
            unfit, fit = _set(False), _set(True)
            for doc in (unfit, fit):
                await store.add_param_set(doc, parameter_bytes(doc))
            with pytest.raises(ApprovalError) as err:
                await upload_set(store, drv, "arm3", unfit["sha256"], None, unattended=False)
            first = str(err.value)
            await upload_set(store, drv, "arm3", unfit["sha256"], None, unattended=False,
                             force=True)
            await upload_set(store, drv, "arm3", fit["sha256"], None, unattended=False)
            states = [u["state"] for u in await store.uploads("arm3")]
        return [first, *states], len(drv.loaded)

    (message, *states), loaded = asyncio.run(go())
    assert message.startswith("upload refused: parameter set 1 of arm3")
    assert "zz_1 = -63.3" in message and "--method consistent" in message
    assert "robid campaign start NAME --force" in message and "\n" not in message
    assert states == ["sent", "acknowledged", "sent", "acknowledged"] and loaded == 2


def test_campaign_force_and_consistent_method_are_config_keys(tmp_path: Path) -> None:
    cfg = load_daemon_config(write_config(tmp_path, {
        "cal": {**QUICK, "upload": True, "force": True, "method": "consistent"}}))
    camp = cfg.campaigns["cal"]
    assert camp.force is True and camp.method == "consistent"
    with pytest.raises(Exception, match=r"campaigns\.cal\.force: expected true or false"):
        load_daemon_config(write_config(tmp_path, {"cal": {**QUICK, "force": "yes"}}))
