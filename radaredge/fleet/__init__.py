"""Fleet scale: run an exported graph over many drives on Ray Data (:mod:`.pipeline`, writing the
Parquet shards of :mod:`radaredge.data.run_shards`) and build and query place-recognition maps
with FAISS (:mod:`.maps`).

Ray's actors import :mod:`.pipeline` only: numpy, pyarrow, onnxruntime and radaredge's torch-free
modules. This package imports none of its modules itself.
"""
