"""Many seeds of one configuration in one process, each computing its lone run (docs/seeds.md)."""

from sb3_td3x.seeds.batch import SeedBatch, acting_as, current_seed

__all__ = ["SeedBatch", "acting_as", "current_seed"]
