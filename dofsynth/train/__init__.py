"""The networks that learn from dofsynth data (torch lives here only, never on the generation
path): data (shard loader), models (DeepLens lens blur + guided upsampling), loss, loop
(training), checkpoint, infer (`render_photo`), evaluate, config. See docs/training.md."""
