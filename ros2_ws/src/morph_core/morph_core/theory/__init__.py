"""The paper's section III checked numerically: clip probabilities per action dimension, Fisher scaling."""
