"""The engine as the server runs it: tracker parameters and range models from the settings, kernel
warm-up, numba's cache."""
