"""The tools: what runs the services and looks at their runs. Each imports the layers below and
the tools below it only: registry (which services exist), recorder, evaluation (scores against
ground truth, with the readers of a recording it needs), viz (the viewer and the Foxglove export),
launcher (the `falconry` command)."""
