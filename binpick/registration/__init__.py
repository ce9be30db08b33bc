"""PPF registration: the model (model.py), voting, clustering, verification and matching, each
its own module; the settings that are not params in constants.py."""
