"""Image2Sim simulator: geometry, capture readers, splatting, renderer, navigation, NeuralSimulator."""

__version__ = "0.1.0"
