"""What a trained policy is once it leaves training: the checkpoint format, the numpy
policy that acts from it, the actor that chooses which weights act, ONNX export."""
