# One image for every awaremw role (router, gateway, fleet, demo).
FROM python:3.11-slim
WORKDIR /app
COPY pyproject.toml README.md ./
COPY awaremw ./awaremw
COPY nodes ./nodes
COPY broker_cfg ./broker_cfg
RUN pip install --no-cache-dir -e .
ENTRYPOINT ["awaremw"]
