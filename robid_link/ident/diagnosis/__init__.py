"""Diagnosis: where the model fails and which effect is missing; hyper-parameter
profiles, the error ladder and drift across runs."""
