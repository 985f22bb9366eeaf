"""``radaredge quantize``: int8 copies judged by the model's task metric on labelled data, and the
search for the fewest layers to keep in fp32 (:mod:`radaredge.quantizing.search`)."""
