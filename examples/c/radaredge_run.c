/*
 * radaredge_run: run any radaredge .onnx from C, as radaredge.runtime does in Python.
 *
 *   radaredge_run [--threads N] [--timestamps t0,t1,...] [--out DIR] [--no-checks] MODEL.onnx SCAN.bin...
 *
 * One SCAN.bin per frame the graph takes, oldest first: little-endian float32 rows with the
 * card's feature columns (radaredge.features in the graph's metadata), e.g. x, y, z, v_r, rcs.
 * Timestamps are seconds (any epoch: they are made relative in double precision before the graph
 * sees float32); without them the frames are 1 / frame_rate apart.
 *
 * What it does, in radaredge.runtime's order: reads the card, the features and the input roles
 * from the metadata; checks every scan (whole rows, finite values, at most max_points_per_frame
 * points) and the timestamps (strictly increasing), naming the file, point and column of a
 * problem; runs one onnxruntime session with radaredge's options (intra-op threads N, one
 * inter-op thread, sequential, all graph optimisations, session.force_spinning_stop = 1); reports
 * the graph's input_flags output bit by bit (radaredge.input_flags in the metadata); writes each
 * output as DIR/<name>.bin (raw, native byte order) and DIR/summary.json (names, types, shapes).
 * --no-checks skips the client's own checks, so the graph's input_flags show what it masked.
 *
 * Exit codes: 0 success (input_flags bits that only inform, e.g. points out of range, are
 * printed on stderr), 1 the graph flagged wrong input (bit 1 non_finite or 2 time_order, which
 * reach the graph only with --no-checks), 2 bad input or a model that is not a radaredge export,
 * reported as one "error: ..." line on stderr.
 */
#include <errno.h>
#include <math.h>
#include <stdarg.h>
#include <stdint.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#include <onnxruntime_c_api.h>

#define MAX_ITEMS 64
#define INPUT_ERRORS 3      /* input_flags bits 1 (non_finite) and 2 (time_order): the input was wrong */
#define MAX_NAME 128

static const OrtApi *ort;

static void fail(const char *fmt, ...) {
    va_list ap;
    va_start(ap, fmt);
    fputs("error: ", stderr);
    vfprintf(stderr, fmt, ap);
    fputc('\n', stderr);
    va_end(ap);
    exit(2);
}

static void check(OrtStatus *status, const char *what) {
    if (status != NULL) {
        char message[512];
        snprintf(message, sizeof message, "%s", ort->GetErrorMessage(status));
        ort->ReleaseStatus(status);
        fail("onnxruntime: %s: %s", what, message);
    }
}

/* Just after the colon of the member "key": of json (a name in a list is no member), or NULL. */
static const char *json_key(const char *json, const char *key) {
    char quoted[MAX_NAME + 4];
    snprintf(quoted, sizeof quoted, "\"%s\"", key);
    for (const char *p = strstr(json, quoted); p != NULL; p = strstr(p + 1, quoted)) {
        const char *q = p + strlen(quoted);
        while (*q == ' ') q++;
        if (*q == ':') return q + 1;
    }
    return NULL;
}

/* The strings of the JSON array that follows "key": in json (or the whole value when key is
 * NULL). radaredge writes names without escapes, so a quote always ends a string. */
static int json_strings(const char *json, const char *key, char out[][MAX_NAME], int max) {
    const char *p = json;
    if (key != NULL) {
        p = json_key(json, key);
        if (p == NULL) return -1;
    }
    p = strchr(p, '[');
    if (p == NULL) return -1;
    int n = 0;
    for (p++; *p != '\0' && *p != ']'; p++) {
        if (*p != '"') continue;
        const char *end = strchr(p + 1, '"');
        if (end == NULL || n == max || end - p - 1 >= MAX_NAME) return -1;
        memcpy(out[n], p + 1, (size_t)(end - p - 1));
        out[n][end - p - 1] = '\0';
        n++;
        p = end;
    }
    return n;
}

/* The string value of "key": "value" in json; "" when it is null or absent. */
static void json_string(const char *json, const char *key, char *out, size_t size) {
    out[0] = '\0';
    const char *p = json_key(json, key);
    if (p == NULL) return;
    while (*p == ' ') p++;
    if (*p != '"') return;
    const char *end = strchr(p + 1, '"');
    if (end == NULL || (size_t)(end - p - 1) >= size) return;
    memcpy(out, p + 1, (size_t)(end - p - 1));
    out[end - p - 1] = '\0';
}

/* A top-level number "key: value" of the card's YAML, or fallback when the card has none. */
static double card_number(const char *yaml, const char *key, double fallback) {
    size_t n = strlen(key);
    for (const char *line = yaml; line != NULL && *line != '\0'; line = strchr(line, '\n')) {
        if (*line == '\n') line++;
        if (strncmp(line, key, n) == 0 && line[n] == ':') return strtod(line + n + 1, NULL);
    }
    return fallback;
}

static char *metadata(OrtModelMetadata *meta, OrtAllocator *alloc, const char *key, const char *model, int required) {
    char *value = NULL;
    check(ort->ModelMetadataLookupCustomMetadataMap(meta, alloc, key, &value), "reading the metadata");
    if (value == NULL && required)
        fail("%s is not a radaredge export: its metadata has no %s entry", model, key);
    return value;
}

typedef struct {
    float *rows;
    int64_t n;
} Scan;

/* Reads path as float32 rows of `columns` columns, checked as radaredge.runtime checks a frame. */
static Scan read_scan(const char *path, int frame, int columns, char names[][MAX_NAME], int64_t max_points,
                      int checks) {
    FILE *f = fopen(path, "rb");
    if (f == NULL) fail("%s: %s", path, strerror(errno));
    if (fseek(f, 0, SEEK_END) != 0) fail("%s: cannot seek", path);
    long bytes = ftell(f);
    rewind(f);
    long row = (long)columns * (long)sizeof(float);
    if (bytes < 0 || bytes % row != 0)
        fail("%s: %ld bytes is not a whole number of rows of %d float32 columns (%ld bytes each)", path, bytes,
             columns, row);
    Scan s = {NULL, bytes / row};
    if (checks && s.n > max_points)
        fail("frame %d (%s): %lld points, more than the card's max_points_per_frame %lld", frame, path,
             (long long)s.n, (long long)max_points);
    s.rows = malloc(bytes > 0 ? (size_t)bytes : sizeof(float));
    if (s.rows == NULL) fail("%s: out of memory", path);
    if (bytes > 0 && fread(s.rows, 1, (size_t)bytes, f) != (size_t)bytes) fail("%s: short read", path);
    fclose(f);
    if (checks) {
        for (int64_t i = 0; i < s.n * columns; i++) {
            if (!isfinite(s.rows[i]))
                fail("frame %d (%s): non-finite value %g at point %lld, column '%s'", frame, path, (double)s.rows[i],
                     (long long)(i / columns), names[i % columns]);
        }
    }
    return s;
}

static const char *type_name(ONNXTensorElementDataType t, size_t *size) {
    switch (t) {
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT: *size = 4; return "float32";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_DOUBLE: *size = 8; return "float64";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_INT64: *size = 8; return "int64";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_INT32: *size = 4; return "int32";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_BOOL: *size = 1; return "bool";
        case ONNX_TENSOR_ELEMENT_DATA_TYPE_UINT8: *size = 1; return "uint8";
        default: *size = 0; return "unsupported";
    }
}

static void usage(void) {
    fail("usage: radaredge_run [--threads N] [--timestamps t0,t1,...] [--out DIR] [--no-checks] MODEL.onnx SCAN.bin...");
}

int main(int argc, char **argv) {
    int threads = 2, checks = 1, n_stamps = 0;
    double stamps[MAX_ITEMS];
    const char *out_dir = ".";
    int arg = 1;
    for (; arg < argc && strncmp(argv[arg], "--", 2) == 0; arg++) {
        if (strcmp(argv[arg], "--threads") == 0 && arg + 1 < argc) {
            char *end;
            long t = strtol(argv[++arg], &end, 10);
            if (*end != '\0' || t < 1 || t > 256) fail("--threads: expected an integer from 1 to 256, got %s", argv[arg]);
            threads = (int)t;
        } else if (strcmp(argv[arg], "--timestamps") == 0 && arg + 1 < argc) {
            for (char *p = argv[++arg]; *p != '\0' && n_stamps < MAX_ITEMS;) {
                char *end;
                stamps[n_stamps++] = strtod(p, &end);
                if (end == p || !isfinite(stamps[n_stamps - 1])) fail("--timestamps: cannot read '%s' as seconds", p);
                p = (*end == ',') ? end + 1 : end;
            }
        } else if (strcmp(argv[arg], "--out") == 0 && arg + 1 < argc) {
            out_dir = argv[++arg];
        } else if (strcmp(argv[arg], "--no-checks") == 0) {
            checks = 0;
        } else {
            usage();
        }
    }
    if (arg >= argc) usage();
    const char *model = argv[arg++];

    ort = OrtGetApiBase()->GetApi(ORT_API_VERSION);
    if (ort == NULL) fail("this onnxruntime library does not provide C API version %d", ORT_API_VERSION);
    OrtEnv *env;
    check(ort->CreateEnv(ORT_LOGGING_LEVEL_ERROR, "radaredge", &env), "creating the environment");
    OrtSessionOptions *opts;
    check(ort->CreateSessionOptions(&opts), "session options");
    check(ort->SetIntraOpNumThreads(opts, threads), "intra-op threads");
    check(ort->SetInterOpNumThreads(opts, 1), "inter-op threads");
    check(ort->SetSessionExecutionMode(opts, ORT_SEQUENTIAL), "execution mode");
    check(ort->SetSessionGraphOptimizationLevel(opts, ORT_ENABLE_ALL), "optimisation level");
    check(ort->SetSessionLogSeverityLevel(opts, 3), "log level");
    /* worker threads stop spinning when a run returns: the app needs the cores between scans */
    check(ort->AddSessionConfigEntry(opts, "session.force_spinning_stop", "1"), "force_spinning_stop");
    OrtSession *session;
    FILE *probe = fopen(model, "rb");
    if (probe == NULL) fail("%s: %s", model, strerror(errno));
    fclose(probe);
    check(ort->CreateSession(env, model, opts, &session), model);
    OrtAllocator *alloc;
    check(ort->GetAllocatorWithDefaultOptions(&alloc), "allocator");

    OrtModelMetadata *meta;
    check(ort->SessionGetModelMetadata(session, &meta), "metadata");
    char *card = metadata(meta, alloc, "radaredge.card", model, 1);
    char *features_json = metadata(meta, alloc, "radaredge.features", model, 1);
    char *inputs_json = metadata(meta, alloc, "radaredge.inputs", model, 1);
    char *flags_json = metadata(meta, alloc, "radaredge.input_flags", model, 0);
    char features[MAX_ITEMS][MAX_NAME], frames[MAX_ITEMS][MAX_NAME], stamps_input[MAX_NAME];
    int n_features = json_strings(features_json, NULL, features, MAX_ITEMS);
    int n_frames = json_strings(inputs_json, "frames", frames, MAX_ITEMS);
    json_string(inputs_json, "timestamps", stamps_input, sizeof stamps_input);
    if (n_features < 1 || n_frames < 0) fail("%s: unreadable radaredge.features / radaredge.inputs metadata", model);
    if (n_frames == 0) fail("%s takes no point-cloud frames (a Des4Pos text or fine-stage graph)", model);
    double frame_rate = card_number(card, "frame_rate", 10.0);
    int64_t max_points = (int64_t)card_number(card, "max_points_per_frame", 65536.0);
    printf("model %s: %d frame(s) of [N, %d] float32 columns", model, n_frames, n_features);
    for (int i = 0; i < n_features; i++) printf("%s%s", i ? ", " : " ", features[i]);
    printf("\ncard:\n%s", card);

    if (argc - arg != n_frames) fail("%s takes %d frame(s) (oldest first), got %d scan file(s)", model, n_frames, argc - arg);
    Scan scans[MAX_ITEMS];
    for (int k = 0; k < n_frames; k++) scans[k] = read_scan(argv[arg + k], k, n_features, features, max_points, checks);

    float rel[MAX_ITEMS];
    if (n_stamps == 0) {
        for (int k = 0; k < n_frames; k++) rel[k] = (float)(k / frame_rate);
    } else {
        if (n_stamps != n_frames) fail("--timestamps: expected %d values in seconds, got %d", n_frames, n_stamps);
        for (int k = 1; k < n_frames && checks; k++)
            if (!(stamps[k] > stamps[k - 1]))
                fail("timestamps must increase strictly (oldest frame first), got %.9g after %.9g", stamps[k],
                     stamps[k - 1]);
        for (int k = 0; k < n_frames; k++) rel[k] = (float)(stamps[k] - stamps[0]);     /* differences in double */
    }

    OrtMemoryInfo *mem;
    check(ort->CreateCpuMemoryInfo(OrtArenaAllocator, OrtMemTypeDefault, &mem), "memory info");
    size_t n_inputs;
    check(ort->SessionGetInputCount(session, &n_inputs), "input count");
    if (n_inputs != (size_t)n_frames + (stamps_input[0] ? 1u : 0u))
        fail("%s has %zu inputs; its metadata names %d frame input(s)%s", model, n_inputs, n_frames,
             stamps_input[0] ? " and timestamps" : "");
    const char *input_names[MAX_ITEMS + 1];
    OrtValue *inputs[MAX_ITEMS + 1];
    for (int k = 0; k < n_frames; k++) {
        int64_t shape[2] = {scans[k].n, n_features};
        input_names[k] = frames[k];
        check(ort->CreateTensorWithDataAsOrtValue(mem, scans[k].rows, (size_t)(scans[k].n * n_features) * sizeof(float),
                                                  shape, 2, ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT, &inputs[k]), frames[k]);
    }
    size_t n_in = (size_t)n_frames;
    if (stamps_input[0]) {
        int64_t shape[1] = {n_frames};
        input_names[n_in] = stamps_input;
        check(ort->CreateTensorWithDataAsOrtValue(mem, rel, (size_t)n_frames * sizeof(float), shape, 1,
                                                  ONNX_TENSOR_ELEMENT_DATA_TYPE_FLOAT, &inputs[n_in]), stamps_input);
        n_in++;
    }

    size_t n_out;
    check(ort->SessionGetOutputCount(session, &n_out), "output count");
    if (n_out > MAX_ITEMS) fail("%s has %zu outputs; this client takes at most %d", model, n_out, MAX_ITEMS);
    char *output_names[MAX_ITEMS];
    OrtValue *outputs[MAX_ITEMS] = {0};
    for (size_t i = 0; i < n_out; i++) check(ort->SessionGetOutputName(session, i, alloc, &output_names[i]), "output name");
    check(ort->Run(session, NULL, input_names, (const OrtValue *const *)inputs, n_in,
                   (const char *const *)output_names, n_out, outputs), "run");

    char path[4096];
    snprintf(path, sizeof path, "%s/summary.json", out_dir);
    FILE *summary = fopen(path, "w");
    if (summary == NULL) fail("%s: %s", path, strerror(errno));
    fprintf(summary, "{\"model\": \"%s\", \"threads\": %d, \"outputs\": [", model, threads);
    int flagged = 0;
    for (size_t i = 0; i < n_out; i++) {
        OrtTensorTypeAndShapeInfo *info;
        check(ort->GetTensorTypeAndShape(outputs[i], &info), output_names[i]);
        ONNXTensorElementDataType type;
        size_t rank, count, size;
        int64_t dims[16];
        check(ort->GetTensorElementType(info, &type), output_names[i]);
        check(ort->GetDimensionsCount(info, &rank), output_names[i]);
        if (rank > 16) fail("output %s has rank %zu", output_names[i], rank);
        check(ort->GetDimensions(info, dims, rank), output_names[i]);
        check(ort->GetTensorShapeElementCount(info, &count), output_names[i]);
        ort->ReleaseTensorTypeAndShapeInfo(info);
        const char *tname = type_name(type, &size);
        if (size == 0) fail("output %s has element type %d, which this client does not write", output_names[i], (int)type);
        void *data;
        check(ort->GetTensorMutableData(outputs[i], &data), output_names[i]);
        snprintf(path, sizeof path, "%s/%s.bin", out_dir, output_names[i]);
        FILE *f = fopen(path, "wb");
        if (f == NULL || (count > 0 && fwrite(data, size, count, f) != count)) fail("%s: cannot write", path);
        fclose(f);
        fprintf(summary, "%s{\"name\": \"%s\", \"dtype\": \"%s\", \"shape\": [", i ? ", " : "", output_names[i], tname);
        for (size_t d = 0; d < rank; d++) fprintf(summary, "%s%lld", d ? ", " : "", (long long)dims[d]);
        fprintf(summary, "]}");
        if (strcmp(output_names[i], "input_flags") == 0 && type == ONNX_TENSOR_ELEMENT_DATA_TYPE_INT32) {
            const int32_t *flags = data;
            for (size_t k = 0; k < count; k++) {
                for (int bit = 0; bit < 31; bit++) {
                    if (!(flags[k] & (1 << bit))) continue;
                    char key[16], meaning[256] = "undocumented bit";
                    snprintf(key, sizeof key, "%d", 1 << bit);
                    if (flags_json != NULL) json_string(flags_json, key, meaning, sizeof meaning);
                    fprintf(stderr, "input_flags: frame %zu: bit %d (%s): %s\n", k, bit, key, meaning);
                    if ((1 << bit) & INPUT_ERRORS) flagged = 1;
                }
            }
        }
    }
    fprintf(summary, "]}\n");
    fclose(summary);
    printf("ran %s on %d thread(s); wrote %zu output(s) to %s\n", model, threads, n_out, out_dir);

    for (size_t i = 0; i < n_out; i++) {
        ort->ReleaseValue(outputs[i]);
        check(ort->AllocatorFree(alloc, output_names[i]), "free");
    }
    for (size_t i = 0; i < n_in; i++) ort->ReleaseValue(inputs[i]);
    for (int k = 0; k < n_frames; k++) free(scans[k].rows);
    check(ort->AllocatorFree(alloc, card), "free");
    check(ort->AllocatorFree(alloc, features_json), "free");
    check(ort->AllocatorFree(alloc, inputs_json), "free");
    if (flags_json != NULL) check(ort->AllocatorFree(alloc, flags_json), "free");
    ort->ReleaseModelMetadata(meta);
    ort->ReleaseMemoryInfo(mem);
    ort->ReleaseSession(session);
    ort->ReleaseSessionOptions(opts);
    ort->ReleaseEnv(env);
    return flagged ? 1 : 0;
}
