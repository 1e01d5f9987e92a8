"""A third party's driver, as its own package (tests/support/plugins/dt_driver_plugin), registers by
entry point, is chosen and checked from the runtime YAML like a built-in one, and passes the
conformance suite; uninstalled, it is gone."""
from __future__ import annotations

import contextlib

import pytest

from drivers import registry
from drivers.base import LaserTracker
from dt_kernel.errors import ConfigError
from dt_runtime.service.runtime_config import load_runtime_config
from tests.support.plugin_install import installed
from tests.support.conformance import run_suite

ENTRY_POINTS = {"cobot_dt.drivers.tracker": {"scripted": "dt_driver_plugin:ScriptedTracker"}}


@pytest.fixture
def plugin(tmp_path):
    (tmp_path / "site").mkdir()
    with installed(tmp_path / "site", "dt_driver_plugin", ENTRY_POINTS, registry.reload) as known:
        yield known
    assert "scripted" not in registry.known("tracker")  # uninstalled: the registry forgets it


def test_the_plugin_is_registered_by_its_entry_point(plugin):
    assert "scripted" in plugin["tracker"] and plugin["robot"] == sorted(registry.BUILTIN["robot"])
    e = registry.entries("tracker")["scripted"]
    assert e.package == "dt-driver-plugin" and e.target == "dt_driver_plugin:ScriptedTracker"
    assert isinstance(registry.create("tracker", "scripted"), LaserTracker)


@pytest.mark.parametrize("options", [{"seed": 3}, {"beam_broken_every": 2, "noise_m": 0.0}])
def test_the_plugin_passes_the_conformance_suite(plugin, options):
    @contextlib.contextmanager
    def factory():
        drv = registry.create("tracker", "scripted")
        try:
            yield drv, options
        finally:
            drv.close()

    assert run_suite("tracker", factory) == ["tracker_satisfies_protocol_and_lifecycle_order",
                                             "tracker_measure_is_consistent"]


def test_the_plugin_is_configured_from_the_runtime_yaml_like_any_driver(plugin, tmp_path):
    cfg = tmp_path / "runtime.yaml"
    cfg.write_text("twin: x\ndrivers: {tracker: {kind: scripted, distance_m: 3.0, seed: 2}}\n")
    assert load_runtime_config(cfg).drivers.tracker.options == {"distance_m": 3.0, "seed": 2}
    cfg.write_text("twin: x\ndrivers: {tracker: {kind: scripted, distance_m: -3.0}}\n")
    with pytest.raises(ConfigError) as ei:  # its own options model, checked when the file is read
        load_runtime_config(cfg)
    assert (ei.value.file, ei.value.key, ei.value.value) == (str(cfg), "drivers.tracker.distance_m", -3.0)
