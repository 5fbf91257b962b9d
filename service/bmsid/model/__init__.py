"""The battery model (pure numpy): OCV curve, hysteresis, exact ZOH simulator, bilinear ARX map."""
