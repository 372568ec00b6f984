# One image for every awaremw role (router, gateway, fleet, demo).
#
# PYTHON_IMAGE: any image with Python 3.11+ and pip on PATH. Where no container
# registry is reachable, tests/containers/run.sh builds a stand-in from Debian
# bookworm (debootstrap) and passes it here.
ARG PYTHON_IMAGE=python:3.11-slim
FROM ${PYTHON_IMAGE}
WORKDIR /app
# Dependencies first (a layer that only changes with pyproject.toml).
COPY pyproject.toml ./
RUN python -c "import tomllib; print('\n'.join(tomllib.load(open('pyproject.toml', 'rb'))['project']['dependencies']))" > /tmp/requirements.txt \
    && pip install --no-cache-dir -r /tmp/requirements.txt "setuptools>=68" \
    && rm /tmp/requirements.txt
# Then the project itself, a real (non-editable) install: the shipped deployments
# come as package data. .dockerignore keeps caches, venvs and git out.
COPY . ./
RUN pip install --no-cache-dir --no-deps --no-build-isolation . \
    && install -m 0755 containers/fleet-part.sh /usr/local/bin/awaremw-fleet-part \
    && install -m 0755 containers/with-secrets.sh /usr/local/bin/awaremw-with-secrets \
    && awaremw --help >/dev/null
ENTRYPOINT ["awaremw"]
