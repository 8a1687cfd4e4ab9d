"""The virtual machine: true errors, campaign plans, rendered images with their truth, and statistics of that truth."""
