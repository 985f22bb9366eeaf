"""The export verb's machinery: torch -> ONNX for every graph of a model (:mod:`.graphs`, the one
``torch.onnx.export`` call in :mod:`.onnx_call`), int8 copies (:mod:`.quantize`) and their
calibration data (:mod:`.calibration`). The verb itself is :func:`radaredge.api.export`."""
