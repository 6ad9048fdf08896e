"""Training of the Edge pose network on frames rendered by our scene (needs torch; the runtime
does not): ``dataset`` renders labelled frames, ``model`` is the network, ``train`` trains and
exports ``domain/models/pose.onnx`` with its record ``pose.json``."""
