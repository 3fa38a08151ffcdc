"""``PingProducts._of`` (how ``process_ping`` builds its result) gives what the dataclass
``__init__`` gives."""

from __future__ import annotations

import dataclasses

from sonarmap import preset
from sonarmap.pipeline import PingProducts, PipelineConfig, process_ping
from sonarmap.simulate import scene_from_name, simulate_ping


def test_products_built_without_init_equal_the_dataclass() -> None:
    g = preset("didson-hf")
    ping = simulate_ping(scene_from_name("hull", geometry=g), g, seed=2).ping
    out = process_ping(ping, PipelineConfig(), keep_labels=True)
    fields = {f.name: getattr(out, f.name) for f in dataclasses.fields(PingProducts)}
    again = PingProducts(**fields)
    assert list(vars(again)) == list(vars(out))
    assert all(getattr(again, k) is v for k, v in fields.items())
    assert out.flagged == again.flagged
