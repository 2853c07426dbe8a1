"""decima_client: submit volumes to a decima-server, watch the jobs, fetch the meshes.

    import decima_client
    client = decima_client.Client("127.0.0.1:50051", token=None)
    job = client.submit("head.nii.gz", regions=3, target_reduction=0.5)
    for event in job.watch():
        print(event.progress.stage, event.progress.fraction)
    job.wait()
    paths = job.fetch("result/")

Errors are the typed exceptions of decima_client.errors (DecimaError and its subclasses), whose
str() is the line the `decima` CLI prints for the same failure. The generated gRPC stubs are in
decima_client.proto (jobs_pb2, volumes_pb2, ...).
"""
from . import errors
from ._client import DEFAULT_SERVER, Client, Job, overall_fraction
from .errors import (DecimaError, InputError, JobCancelled, JobFailed, MissingDependencyError,
                     MissingInputError, ServerUnreachable)

__version__ = "0.1.0"
__all__ = ["Client", "Job", "DEFAULT_SERVER", "overall_fraction", "errors", "DecimaError",
           "InputError", "MissingInputError", "ServerUnreachable", "JobFailed", "JobCancelled",
           "MissingDependencyError"]
