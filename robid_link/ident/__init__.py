"""The worker: from a robot description and logs to an identified, validated and diagnosed
model. Rooms: model, data, fit, diagnosis, elastic, excite, report; ``runner`` runs one job."""

import os

# OpenMP threads (numba's parallel kernels; the runtime is loaded with Pinocchio and reads this
# then) sleep between parallel regions instead of spinning: on a shared machine a spinning
# worker holds the core that the kernel's other half, or another process, needs — the
# regressor over 100k samples in 2048-sample calls took 3.6 µs a sample instead of 0.8 under
# load 17. A user's choice stands.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
