"""Measurements on top of the model and the dataset: speed (``bench``), agreement
with physics (``pushsim``, ``validation``) and the policy experiment.
"""
