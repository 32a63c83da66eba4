"""Analysis of detector images: STSA correction, gradients, height maps, design tools (numpy)."""
