"""Making a data set from a recipe: plan (the shards), worker (one process's part: the pure
`generate_shard`), executors (who runs the shards: local processes, Ray), folder (what OUT may
hold, resume, temp files) and run (`generate`: the one driver, lock to manifest)."""
from dofsynth.generate.executors import Executor, LocalExecutor, RayExecutor, make_executor
from dofsynth.generate.folder import OutputNotEmptyError, ResumeError
from dofsynth.generate.plan import ShardTask, parse_shard_range, plan_shards, plan_split
from dofsynth.generate.run import GenerateResult, generate
from dofsynth.generate.worker import generate_shard, render_one

__all__ = ["Executor", "GenerateResult", "LocalExecutor", "OutputNotEmptyError", "RayExecutor", "ResumeError",
           "ShardTask", "generate", "generate_shard", "make_executor", "parse_shard_range", "plan_shards",
           "plan_split", "render_one"]
