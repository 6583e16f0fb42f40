"""The worker: from a robot description and logs to an identified, validated and diagnosed
model. Rooms: model, data, fit, diagnosis, elastic, excite, report; ``runner`` runs one job."""
