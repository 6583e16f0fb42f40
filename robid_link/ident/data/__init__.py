"""The data room: log files in, checked and preprocessed joint-side samples out."""
