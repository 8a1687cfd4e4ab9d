"""What the identified model says and where it fails: compensation, verification, residuals, diagnosis, drift."""
