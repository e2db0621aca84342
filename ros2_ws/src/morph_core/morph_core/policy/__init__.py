"""The graph actor-critic: batched chains, the chain NNConv, the torch network and its NumPy twin for inference."""
