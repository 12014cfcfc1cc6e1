"""Front ends that run on the car or beside it (no JAX imported here).

`SceneSink`: the scene of live or replayed predictions for Foxglove (WebSocket and MCAP).
Names are imported on first use, so registering `fpe view` keeps `fpe --help` fast.
"""

__all__ = ["SceneSink"]


def __getattr__(name: str):
    if name == "SceneSink":
        from fpe_jax.node._foxglove import SceneSink

        return SceneSink
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
