"""sb3-td3x: a fast, hackable TD3 for Stable-Baselines3."""

from sb3_td3x.seeds import SeedBatch
from sb3_td3x.td3x import DDPG, PRESETS, TD3X, CnnPolicy, MlpPolicy, MultiInputPolicy, TD3XPolicy, preset_kwargs

__version__ = "0.1.0"

__all__ = ["DDPG", "PRESETS", "TD3X", "CnnPolicy", "MlpPolicy", "MultiInputPolicy", "SeedBatch", "TD3XPolicy", "__version__", "preset_kwargs"]
