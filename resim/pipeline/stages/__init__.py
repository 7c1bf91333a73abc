"""Pipeline stages, in order (each a callable class: heavy set-up in ``__init__``, ``__call__`` on batches).

1. enumerate (driver side, :func:`resim.pipeline.runner.enumerate_units`)  2. cut  3. label  4. balance
5. encode (resize/crop + VAE)  6. prompts (T5, once per distinct text)  7. write (shards + commit).
"""
from resim.pipeline.stages.balance import BalanceStage
from resim.pipeline.stages.cut import CutStage
from resim.pipeline.stages.encode import EncodeStage
from resim.pipeline.stages.label import LabelStage
from resim.pipeline.stages.prompts import PromptStage
from resim.pipeline.stages.write import WriteStage

# Unit stages in execution order; names match config keys under ray.stages.
UNIT_STAGES = (("cut", CutStage), ("label", LabelStage), ("balance", BalanceStage),
               ("encode", EncodeStage), ("write", WriteStage))

__all__ = ["CutStage", "LabelStage", "BalanceStage", "EncodeStage", "PromptStage", "WriteStage", "UNIT_STAGES"]
