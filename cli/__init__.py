"""The `veinmosaic` command line, the launcher of the service's processes, and the upload client."""
