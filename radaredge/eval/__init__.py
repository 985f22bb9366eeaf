"""The eval verb's machinery: place-recognition Recall@N (:mod:`.places`), Des4Pos localisation
recall (:mod:`.localisation`) and which task evaluates each model (:mod:`.tasks`). The verb is
:func:`radaredge.api.evaluate`."""
