"""What a person reads: figures and report files."""
