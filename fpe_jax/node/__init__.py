"""Front ends that run on the car or beside it (no JAX imported here).

`SceneSink`: the scene of live or replayed predictions for Foxglove (WebSocket and MCAP).
"""

from fpe_jax.node._foxglove import SceneSink

__all__ = ["SceneSink"]
