"""TD3's successors, each a short subclass of :class:`~sb3_td3x.TD3X` that overrides a few hooks (docs/variants.md).

- :class:`TD3LAP`: LAP prioritised replay and its loss, as TD7 uses them (Fujimoto et al. 2020, 2023).
- :class:`TD3NStep`: n-step returns, n = 3 (SB3's ``n_steps``).
- :class:`TD3LayerNorm`: LayerNorm after each hidden layer of the critics.
- :class:`TD3C51`: FastTD3's categorical (C51) critic (Seo et al. 2025; Bellemare et al. 2017).

Each has its config, ``conf/algo/<name>.yaml``: ``python run.py algo=td3_lap env=hopper``.
"""

from sb3_td3x.variants.c51 import TD3C51, categorical_projection
from sb3_td3x.variants.lap import TD3LAP, lap_huber
from sb3_td3x.variants.layernorm import TD3LayerNorm
from sb3_td3x.variants.nstep import TD3NStep

__all__ = ["TD3C51", "TD3LAP", "TD3LayerNorm", "TD3NStep", "categorical_projection", "lap_huber"]
