# One image for every awaremw role (router, gateway, fleet, demo).
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY awaremw ./awaremw
COPY broker_cfg ./broker_cfg
# A real install: the shipped deployments (awaremw/deployments/*.toml) come as
# package data, so `awaremw fleet fire` works from any directory.
RUN pip install --no-cache-dir .
ENTRYPOINT ["awaremw"]
