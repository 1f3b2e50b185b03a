"""Import the AMULED authors' published artefacts (``temetski/moral_agent``)."""
