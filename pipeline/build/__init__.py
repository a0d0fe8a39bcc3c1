"""The dataset job: corpus -> fan-out of ``pipeline.model.evaluation`` over objects
-> rows -> shards written atomically -> manifest; ``verify`` checks a finished
dataset.  Depends on ``pipeline.model`` and ``schema``.
"""
