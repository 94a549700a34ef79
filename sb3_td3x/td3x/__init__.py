from sb3_td3x.td3x.policies import CnnPolicy, MlpPolicy, MultiInputPolicy, TD3XCritic, TD3XPolicy
from sb3_td3x.td3x.presets import DDPG, PRESETS, preset_kwargs
from sb3_td3x.td3x.td3x import TD3X, UnsupportedActionSpace

__all__ = [
    "DDPG",
    "PRESETS",
    "TD3X",
    "CnnPolicy",
    "MlpPolicy",
    "MultiInputPolicy",
    "TD3XCritic",
    "TD3XPolicy",
    "UnsupportedActionSpace",
    "preset_kwargs",
]
