"""The engine path shared by the server, the evaluation and live sessions: sensor messages in
time order (``messages``), fed to the fusion (``estimator.pipeline.Fusion``) by one driver."""
