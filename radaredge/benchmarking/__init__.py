"""The bench verb's machinery: the report and the per-backend rows (:mod:`.harness`), the
interleaved 2-core timing harness (:mod:`.timing`), onnxruntime profiles and stage splits
(:mod:`.profiling`), MAC counting (:mod:`.macs`) and the models' own bench tasks
(:mod:`.tasks`). The verb is :func:`radaredge.api.bench`."""
