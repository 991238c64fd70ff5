"""Black-box Reachability-based Safety Layer for TorchRL."""
