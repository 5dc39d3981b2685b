"""Training of the trunk detector (needs the training extra: torch, torchvision)."""
