"""Quality assurance of finished data sets (they read shards, never write them): dataset (the
reader), draw (shared drawing primitives), sheets (contact sheets), html (the QA page), stats
(histograms), schema (record and pixel checks) and verify (`dofsynth verify`)."""
