"""The GP experts' training: datasets from a data run's recording, fitting, saving and loading."""
