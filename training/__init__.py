"""Offline model building from the domain's code: the Edge pose network (``perception``) and the
abstract loops' frame-size and estimator-error model (``frame_model``)."""
